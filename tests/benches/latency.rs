//! Sample-to-command round trip of the service at 100 Hz on loopback, measured beside a
//! plain Zenoh publish/echo between two sessions in the same run.
//!
//! `cargo bench -p system-tests --bench latency [-- SECONDS]` (default 20 s each). Both use
//! the same plumbing (express, real-time priority, drop on congestion; the echo side
//! answers inside zenoh's callback, as the service does when its worker is free; both
//! round trips run from just before the put to the reply's callback). What the ratio holds
//! beyond the service's decoding, control step and encoding: the agent's encoding of its
//! sample, and a sample that carries its last three predecessors again (`resend`), longer
//! than the echo's 70 bytes.

use std::time::Duration;

use mfc_lab::harness::{run_plant, service_config, PlantSpec, ServiceHandle};
use plant::record::percentile;
use plant::scenario::{load_scenario, shipped_controller};
use tokio::time::Instant;
use transport::ZenohArgs;
use zenoh::Wait;

async fn echo(seconds: f64) -> anyhow::Result<Vec<f64>> {
    let port = transport::free_local_port()?;
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let a = ZenohArgs::loopback(Some(endpoint.clone()), vec![])
        .open()
        .await?;
    let b = ZenohArgs::loopback(None, vec![endpoint]).open().await?;
    let pong = transport::control_publisher(&b, "bench/pong".into()).await?;
    // Answered inside zenoh's callback (a blocking put is zenoh's own way there), as the
    // service answers a sample when its worker is free.
    let _ping_sub = b
        .declare_subscriber("bench/ping")
        .callback(move |s| {
            let _ = pong.put(s.payload().to_bytes().into_owned()).wait();
        })
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let (rtx, mut rrx) = tokio::sync::mpsc::channel::<Instant>(256);
    let _pong_sub = a
        .declare_subscriber("bench/pong")
        .callback(move |_| {
            let _ = rtx.try_send(Instant::now());
        })
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let ping = transport::control_publisher(&a, "bench/ping".into()).await?;
    tokio::time::sleep(Duration::from_millis(300)).await;
    let payload = vec![0x5au8; 70]; // the size of an encoded AERO sample
    let period = Duration::from_millis(10);
    let start = Instant::now();
    let mut rtts = Vec::new();
    for k in 0..(seconds * 100.0) as u32 {
        let deadline = start + period * k;
        tokio::time::sleep_until(deadline).await;
        let sent = Instant::now();
        ping.put(payload.clone())
            .await
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        if let Ok(Some(at)) = tokio::time::timeout_at(deadline + period, rrx.recv()).await {
            rtts.push((at - sent).as_secs_f64() * 1e6);
        }
    }
    let _ = a.close().await;
    let _ = b.close().await;
    Ok(rtts)
}

#[tokio::main(flavor = "multi_thread")]
async fn main() -> anyhow::Result<()> {
    let seconds: f64 = std::env::args()
        .skip(1)
        .find_map(|a| a.parse().ok())
        .unwrap_or(20.0);
    let mut e = echo(seconds).await?;
    e.sort_by(f64::total_cmp);

    let mut s = load_scenario("2")?;
    s.duration = seconds;
    let c = shipped_controller("ipd")?;
    let service = ServiceHandle::start(service_config(&s, &c, &["bench".into()]), None).await?;
    let run = run_plant(
        vec![service.endpoint.clone()],
        PlantSpec::new(&s, &c, "bench"),
        true,
    )
    .await?;
    service.stop().await?;
    let report = run.report;
    let (e50, e99) = (percentile(&e, 0.5), percentile(&e, 0.99));
    let (l50, l99) = (report.rtt_p50_us, report.rtt_p99_us);
    println!("round trip at 100 Hz on loopback, {seconds:.0} s each, one run:");
    println!("| path | samples | p50 (us) | p99 (us) |");
    println!("|---|---:|---:|---:|");
    println!(
        "| plain zenoh publish/echo | {} | {e50:.0} | {e99:.0} |",
        e.len()
    );
    println!(
        "| sample -> controller service -> command | {} | {l50:.0} | {l99:.0} |",
        report.counters.commands
    );
    println!(
        "| ratio service / echo | | {:.2} | {:.2} |",
        l50 / e50,
        l99 / e99
    );
    println!(
        "missing commands: {} of {} periods",
        report.counters.missing, report.counters.periods
    );
    Ok(())
}

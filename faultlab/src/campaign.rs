//! The campaign: for each profile and link, a controller service and simulated AEROs (one
//! per controller, side by side on the same impaired link) run a scenario through the
//! relay, in real time.

use std::net::SocketAddr;

use controller_service::config::ServiceConfig;
use controller_service::{service, Registry};
use plant_agent::agent::{run_agent, AgentReport, Fallback};
use plant_agent::demo::{agent_config, rand_id, service_config};
use plant_agent::plant::SimPlant;
use plant_agent::scenario::{ControllerSet, Scenario};
use serde::{Deserialize, Serialize};
use transport::ZenohArgs;

use crate::profile::Profile;
use crate::relay::{Link, Relay, RelayStats};

/// One controller's run under one profile on one link.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CaseResult {
    /// Profile name.
    pub profile: String,
    /// Link.
    pub link: Link,
    /// Controller name.
    pub controller: String,
    /// The agent's report.
    pub report: AgentReport,
    /// RMS over the unimpaired run on the same link, per channel (filled by the campaign).
    pub rms_ratio: Vec<f64>,
    /// What the relay did.
    pub relay: RelayStats,
    /// The run, period by period (only when recorded).
    #[serde(skip)]
    pub rows: Vec<plant_agent::agent::Row>,
}

/// Open a session that does not gossip: fault tests must not let peers find a way
/// around the relay.
async fn session(args: ZenohArgs) -> anyhow::Result<zenoh::Session> {
    let mut config = args.to_config()?;
    config
        .insert_json5("scouting/gossip/enabled", "false")
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    zenoh::open(config)
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))
}

/// Wait (at most 5 s) until the service reports round trips for every device.
async fn wait_until_flowing(service_endpoint: &str, ids: &[String]) {
    let Ok(probe) = session(ZenohArgs::loopback(
        None,
        vec![service_endpoint.to_string()],
    ))
    .await
    else {
        return;
    };
    let deadline = tokio::time::Instant::now() + std::time::Duration::from_secs(5);
    while tokio::time::Instant::now() < deadline {
        let mut flowing = 0;
        for id in ids {
            let status = transport::get_first(&probe, &protocol::keys::status(id), None)
                .await
                .ok()
                .and_then(|b| protocol::decode::<protocol::pb::DeviceStatus>(&b).ok());
            if status.is_some_and(|st| st.loop_rtt.is_some_and(|l| l.count >= 5)) {
                flowing += 1;
            }
        }
        if flowing == ids.len() {
            break;
        }
        tokio::time::sleep(std::time::Duration::from_millis(50)).await;
    }
    let _ = probe.close().await;
}

/// Options of a case.
#[derive(Debug, Clone)]
pub struct CaseOptions {
    /// Periods to hold before falling back.
    pub hold_periods: u32,
    /// What to fall back to.
    pub fallback: Fallback,
    /// Oldest command worth applying (periods).
    pub max_age: u32,
    /// Keep every period's row in the results.
    pub record: bool,
}

impl Default for CaseOptions {
    fn default() -> Self {
        Self {
            hold_periods: 5,
            fallback: Fallback::Local,
            max_age: plant_agent::demo::DEFAULT_MAX_AGE,
            record: false,
        }
    }
}

/// Run every controller of `controllers` on `scenario`, side by side, through a relay
/// impairing `link` with `profile`.
pub async fn run_case(
    scenario: &Scenario,
    controllers: &[ControllerSet],
    profile: &Profile,
    link: Link,
    options: &CaseOptions,
) -> anyhow::Result<Vec<CaseResult>> {
    let port = match link {
        Link::Tcp => transport::free_local_port()?,
        Link::Udp => transport::free_udp_port()?,
    };
    let target: SocketAddr = format!("127.0.0.1:{port}").parse()?;
    let mut config = ServiceConfig::default();
    let ids: Vec<String> = controllers
        .iter()
        .map(|c| format!("aero-{}", c.name))
        .collect();
    for (c, id) in controllers.iter().zip(&ids) {
        config
            .devices
            .extend(service_config(scenario, c, std::slice::from_ref(id)).devices);
    }
    let registry = Registry::new(config)?;
    let svc_session = session(ZenohArgs::loopback(
        Some(format!("{}/{target}", link.scheme())),
        vec![],
    ))
    .await?;
    let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
    let svc = tokio::spawn(service::run(svc_session, registry, async {
        let _ = stop_rx.await;
    }));
    // Sessions establish through a transparent relay; it starts impairing once the loops
    // run (zenoh does not retransmit handshakes or declarations lost on a UDP link).
    let relay = Relay::start(link, "127.0.0.1:0".parse()?, target, profile, false).await?;
    let endpoint = format!("{}/{}", link.scheme(), relay.listen);

    let mut tasks = Vec::new();
    for (i, (c, id)) in controllers.iter().zip(&ids).enumerate() {
        let record = options.record.then(|| {
            std::env::temp_dir().join(format!("faultlab-{}-{id}.csv", std::process::id()))
        });
        let mut cfg = agent_config(
            scenario,
            c,
            id,
            options.hold_periods,
            options.fallback,
            record,
        );
        cfg.max_age = options.max_age;
        let params = scenario.plant.clone();
        let seed = scenario.seed;
        let endpoint = endpoint.clone();
        tasks.push(tokio::spawn(async move {
            let s = session(ZenohArgs::loopback(None, vec![endpoint])).await?;
            let mut plant = SimPlant::new(params, seed)?;
            let r = run_agent(&s, &mut plant, &cfg, rand_id(i as u64)).await;
            let _ = s.close().await;
            anyhow::Ok(r?)
        }));
    }
    // Arm once every plant has received commands (its samples report a round trip): by
    // then every session is up and every declaration has crossed the link.
    wait_until_flowing(&format!("{}/{target}", link.scheme()), &ids).await;
    relay.arm();
    let mut results = Vec::new();
    for (task, c) in tasks.into_iter().zip(controllers) {
        let (report, rows) = task.await??;
        results.push(CaseResult {
            profile: profile.name.clone(),
            link,
            controller: c.name.clone(),
            report,
            rms_ratio: Vec::new(),
            relay: relay.stats(),
            rows,
        });
    }
    drop(relay);
    let _ = stop_tx.send(());
    svc.await??;
    Ok(results)
}

/// The whole campaign.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Campaign {
    /// Scenario name.
    pub scenario: String,
    /// Duration of each run (s).
    pub duration: f64,
    /// Every case.
    pub cases: Vec<CaseResult>,
}

impl Campaign {
    /// Fill each case's RMS ratio from the `none` profile on the same link and controller.
    pub fn compute_ratios(&mut self, baseline: &str) {
        let base: Vec<(Link, String, Vec<f64>)> = self
            .cases
            .iter()
            .filter(|c| c.profile == baseline)
            .map(|c| {
                (
                    c.link,
                    c.controller.clone(),
                    c.report.channels.iter().map(|m| m.rms).collect(),
                )
            })
            .collect();
        for c in &mut self.cases {
            if let Some((_, _, b)) = base
                .iter()
                .find(|(l, n, _)| *l == c.link && *n == c.controller)
            {
                c.rms_ratio = c
                    .report
                    .channels
                    .iter()
                    .zip(b)
                    .map(|(m, b)| m.rms / b)
                    .collect();
            }
        }
    }

    /// The table in Markdown.
    pub fn markdown(&self) -> String {
        use std::fmt::Write as _;
        let mut out = String::new();
        let _ = writeln!(
            out,
            "| profile | link | controller | azimuth RMS ratio | pitch RMS ratio | pitch RMS (rad) | pitch worst (rad) | periods without command | applied late | stale | fallbacks | RTT p50 / p99 (ms) |"
        );
        let _ = writeln!(
            out,
            "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
        );
        for c in &self.cases {
            let r = &c.report;
            let ratio = |i: usize| c.rms_ratio.get(i).map_or("-".into(), |x| format!("{x:.2}"));
            let _ = writeln!(
                out,
                "| {} | {} | {} | {} | {} | {:.2e} | {:.3} | {:.1}% | {} | {} | {} | {:.1} / {:.1} |",
                c.profile,
                c.link.scheme(),
                c.controller,
                ratio(0),
                ratio(1),
                r.channels.get(1).map_or(0.0, |m| m.rms),
                r.channels.get(1).map_or(0.0, |m| m.max_abs),
                100.0 * r.missing as f64 / r.periods.max(1) as f64,
                r.late,
                r.stale,
                r.fallbacks,
                r.rtt_p50_us / 1000.0,
                r.rtt_p99_us / 1000.0
            );
        }
        out
    }
}

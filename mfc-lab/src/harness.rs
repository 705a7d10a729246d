//! The one harness that starts a controller service and plants in-process, each in its
//! own Zenoh session on loopback (peers, multicast scouting off), as in production. The
//! demo, the fault campaign, the system tests and the benchmarks all use it, so there is
//! one way to set up a networked run.

use anyhow::Context as _;
use controller_service::config::{DeviceChannel, DeviceSpec, ServiceConfig};
use controller_service::service;
use plant::scenario::{ControllerSet, Scenario};
use plant_agent::agent::{self, AgentRun, LoopConfig};
use plant_agent::safety::{FallbackPolicy, SafetyConfig};
use transport::ZenohArgs;
use zenoh::Session;

/// The safety settings of the demo and the tests: the agent's defaults (hold 5 periods,
/// then the local controller; commands up to 10 periods old are still applied).
pub fn default_safety(scenario: &Scenario) -> SafetyConfig {
    SafetyConfig {
        period: scenario.period,
        max_age: SafetyConfig::DEFAULT_MAX_AGE,
        hold_periods: SafetyConfig::DEFAULT_HOLD_PERIODS,
        fallback: FallbackPolicy::LocalController,
    }
}

/// The service configuration that serves `ids` with `controller` on `scenario`.
pub fn service_config(
    scenario: &Scenario,
    controller: &ControllerSet,
    ids: &[String],
) -> ServiceConfig {
    ServiceConfig {
        controller_id: "controller-1".into(),
        devices: ids
            .iter()
            .map(|id| DeviceSpec {
                id: id.clone(),
                channels: scenario
                    .channels
                    .iter()
                    .zip(&controller.channels)
                    .map(|(c, law)| DeviceChannel {
                        law: *law,
                        output: c.output,
                        reference: c.reference.clone(),
                        // The envelope is the scenario's actuator range (its output map).
                        envelope: None,
                        // The bounds derived from the device and the table's.
                        bounds: Default::default(),
                        range: None,
                    })
                    .collect(),
                prediction: Default::default(),
            })
            .collect(),
        ..ServiceConfig::default()
    }
}

/// Open a peer session on loopback. `gossip = false` for fault tests: peers must not find a
/// way around the relay.
pub async fn open_session(
    listen: Option<String>,
    connect: Vec<String>,
    gossip: bool,
) -> anyhow::Result<Session> {
    open_config(loopback_config(listen, connect, gossip)?).await
}

fn loopback_config(
    listen: Option<String>,
    connect: Vec<String>,
    gossip: bool,
) -> anyhow::Result<zenoh::Config> {
    let mut config = ZenohArgs::loopback(listen, connect).to_config()?;
    if !gossip {
        config
            .insert_json5("scouting/gossip/enabled", "false")
            .map_err(|e| anyhow::anyhow!("{e}"))?;
    }
    Ok(config)
}

async fn open_config(config: zenoh::Config) -> anyhow::Result<Session> {
    zenoh::open(config)
        .await
        .map_err(|e| anyhow::anyhow!("opening a zenoh session: {e}"))
}

/// A controller service running in this process.
pub struct ServiceHandle {
    /// Endpoint the service listens on.
    pub endpoint: String,
    /// Address of its metrics endpoint, if its configuration asks for one.
    pub metrics: Option<std::net::SocketAddr>,
    /// The fleet's secret, if it was started with keys ([`ServiceHandle::start_keyed`]).
    pub secret: Option<protocol::auth::Secret>,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    task: tokio::task::JoinHandle<Result<(), service::ServiceError>>,
    observers: controller_service::observe::Observers,
    metrics_stop: Option<(
        tokio::sync::oneshot::Sender<()>,
        tokio::task::JoinHandle<()>,
    )>,
}

impl ServiceHandle {
    /// Start a service for `config` listening on `endpoint` (`None`: a free TCP port on
    /// loopback). It runs open (no keys): what tests that put hand-made messages want.
    pub async fn start(config: ServiceConfig, endpoint: Option<String>) -> anyhow::Result<Self> {
        Self::start_with(config, endpoint, true, None).await
    }

    /// As [`ServiceHandle::start`], with keys made now ([`ServiceHandle::secret`]): plants
    /// and gateways then need their key (`secret.device(id)`, `secret.gateway(id)`), as in
    /// a deployment `mfc-deploy` generated.
    pub async fn start_keyed(
        config: ServiceConfig,
        endpoint: Option<String>,
    ) -> anyhow::Result<Self> {
        let secret = protocol::auth::Secret::random()?;
        tracing::info!("auth: keys made at start (no deployment: they live as long as this run)");
        Self::start_with(config, endpoint, true, Some(secret)).await
    }

    /// As [`ServiceHandle::start`], choosing whether the service's session gossips and
    /// giving it the fleet's secret (`None`: open).
    pub async fn start_with(
        config: ServiceConfig,
        endpoint: Option<String>,
        gossip: bool,
        secret: Option<protocol::auth::Secret>,
    ) -> anyhow::Result<Self> {
        let endpoint = match endpoint {
            Some(e) => e,
            None => format!("tcp/127.0.0.1:{}", transport::free_local_port()?),
        };
        // As the service's binary: the recording and the metrics its configuration asks for.
        let (observers, earlier) = controller_service::cli::observers(&config)?;
        let mut metrics = None;
        let mut metrics_stop = None;
        if let (Some(spec), Some(m)) = (&config.metrics, &observers.metrics) {
            let (tx, rx) = tokio::sync::oneshot::channel::<()>();
            let (addr, task) =
                controller_service::observe::serve_endpoint(spec, m.clone(), async {
                    let _ = rx.await;
                })
                .await?;
            metrics = Some(addr);
            metrics_stop = Some((tx, task));
        }
        let file = std::path::Path::new("service-config.toml");
        let mut registries = controller_service::cli::registries(
            vec![config],
            (secret.clone(), transport::DEFAULT_LINK_LEASE),
            &observers,
            &earlier,
            file,
        )
        .await?;
        let registry = registries.pop().context("one registry")?;
        // As the service's own binary: no message larger than it would count is reassembled.
        let mut zc = loopback_config(Some(endpoint.clone()), vec![], gossip)?;
        transport::bound_messages(&mut zc, protocol::MAX_TRANSPORT_MESSAGE)?;
        let session = open_config(zc).await?;
        let (tx, rx) = tokio::sync::oneshot::channel::<()>();
        let task = tokio::spawn({
            let (session, observers) = (session.clone(), observers.clone());
            async move {
                let r = service::serve(session.clone(), registry, observers, async {
                    let _ = rx.await;
                })
                .await;
                let _ = session.close().await;
                r
            }
        });
        Ok(Self {
            endpoint,
            secret,
            metrics,
            stop: Some(tx),
            task,
            observers,
            metrics_stop,
        })
    }

    /// A client session connected to the service.
    pub async fn client(&self) -> anyhow::Result<Session> {
        open_session(None, vec![self.endpoint.clone()], true).await
    }

    /// Stop the service and wait for it.
    pub async fn stop(mut self) -> anyhow::Result<()> {
        if let Some(tx) = self.stop.take() {
            let _ = tx.send(());
        }
        (&mut self.task).await??;
        if let Some((tx, task)) = self.metrics_stop.take() {
            let _ = tx.send(());
            let _ = task.await;
        }
        if let Some(r) = self.observers.recording.take() {
            tokio::task::spawn_blocking(move || r.finish()).await??;
        }
        Ok(())
    }
}

/// One plant to run through the harness.
#[derive(Debug, Clone)]
pub struct PlantSpec {
    /// The scenario (its plant, channels and references).
    pub scenario: Scenario,
    /// The loop's settings (device id, safety, local controller).
    pub loop_config: LoopConfig,
    /// Noise seed of the built-in simulator.
    pub seed: u64,
}

impl PlantSpec {
    /// Plant `id` on `scenario` with `controller` as its local copy and the default safety
    /// settings.
    pub fn new(scenario: &Scenario, controller: &ControllerSet, id: &str) -> Self {
        Self {
            scenario: scenario.clone(),
            loop_config: LoopConfig::new(scenario, controller, id, default_safety(scenario)),
            seed: scenario.seed,
        }
    }
}

/// Run one plant through its own session connected to `endpoints`, to the end of its
/// scenario.
pub async fn run_plant(
    endpoints: Vec<String>,
    plant: PlantSpec,
    gossip: bool,
) -> anyhow::Result<AgentRun> {
    let session = open_session(None, endpoints, gossip).await?;
    let p = agent::open_plant(&plant.scenario, plant.seed).await?;
    let out = agent::run_loop(
        &session,
        p,
        &plant.loop_config,
        run_id(plant.seed),
        std::future::pending(),
    )
    .await;
    let _ = session.close().await;
    Ok(out?)
}

/// A run id that differs between runs and between plants of one run, and grows from one
/// run to the next as [`plant::run_id`] does (the salt changes its low 16 bits only).
pub fn run_id(salt: u64) -> u64 {
    (plant::run_id() ^ (salt.wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 48)).max(1)
}

/// Start a service for `plants` and run them all concurrently; returns their runs in order.
/// Keys are made at start: every sample and command carries its proof of origin, as in a
/// deployment.
pub async fn run_fleet(
    plants: Vec<PlantSpec>,
    config: ServiceConfig,
) -> anyhow::Result<Vec<AgentRun>> {
    let service = ServiceHandle::start_keyed(config, None).await?;
    let secret = service.secret.clone();
    let mut tasks = Vec::new();
    for mut p in plants {
        p.loop_config.auth = secret.as_ref().map(|s| s.device(&p.loop_config.device_id));
        tasks.push(tokio::spawn(run_plant(
            vec![service.endpoint.clone()],
            p,
            true,
        )));
    }
    let mut runs = Vec::new();
    for t in tasks {
        runs.push(t.await??);
    }
    service.stop().await?;
    Ok(runs)
}

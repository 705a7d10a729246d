//! Helpers for the system tests: a controller service and simulated plants, each in its own
//! Zenoh session on loopback (peers, multicast scouting off), as in production.

use controller_service::{service, Registry, ServiceConfig};
use plant_agent::agent::{run_agent, AgentConfig, AgentReport, Row};
use plant_agent::plant::SimPlant;
use transport::ZenohArgs;
use zenoh::Session;

/// Real-time tests share two cores: they take this lock so that they do not disturb each
/// other's timing.
pub static SERIAL: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

/// A running controller service.
pub struct Service {
    /// Endpoint the service listens on.
    pub endpoint: String,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    task: tokio::task::JoinHandle<Result<(), controller_service::service::ServiceError>>,
}

impl Service {
    /// Start a service for `config` on a free loopback port.
    pub async fn start(config: ServiceConfig) -> anyhow::Result<Self> {
        let port = transport::free_local_port()?;
        let endpoint = format!("tcp/127.0.0.1:{port}");
        let registry = Registry::new(config)?;
        let session = ZenohArgs::loopback(Some(endpoint.clone()), vec![])
            .open()
            .await?;
        let (tx, rx) = tokio::sync::oneshot::channel::<()>();
        let task = tokio::spawn(service::run(session, registry, async {
            let _ = rx.await;
        }));
        Ok(Self {
            endpoint,
            stop: Some(tx),
            task,
        })
    }

    /// A client session connected to the service.
    pub async fn client(&self) -> anyhow::Result<Session> {
        Ok(ZenohArgs::loopback(None, vec![self.endpoint.clone()])
            .open()
            .await?)
    }

    /// Stop the service and wait for it.
    pub async fn stop(mut self) -> anyhow::Result<()> {
        if let Some(tx) = self.stop.take() {
            let _ = tx.send(());
        }
        (&mut self.task).await??;
        Ok(())
    }
}

/// Run one simulated plant through its own session.
pub async fn run_plant(
    endpoint: String,
    params: plant_agent::aero::AeroParams,
    seed: u64,
    config: AgentConfig,
) -> anyhow::Result<(AgentReport, Vec<Row>)> {
    let session = ZenohArgs::loopback(None, vec![endpoint]).open().await?;
    let mut plant = SimPlant::new(params, seed)?;
    let out = run_agent(
        &session,
        &mut plant,
        &config,
        plant_agent::demo::rand_id(seed),
    )
    .await;
    let _ = session.close().await;
    Ok(out?)
}

/// Send a query on `key` (with `payload`, if any) and decode its first reply.
pub async fn query<M: protocol::Versioned>(
    session: &Session,
    key: String,
    payload: Option<Vec<u8>>,
) -> anyhow::Result<M> {
    let bytes = transport::get_first(session, &key, payload).await?;
    Ok(protocol::decode(&bytes)?)
}

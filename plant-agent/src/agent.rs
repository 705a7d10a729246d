//! The networked loop of the plant agent: thin wiring around [`crate::safety`].
//!
//! It owns what the pure core must not: the clock, the plant and the network. Every
//! period `k` (deadline `t_k = start + k h`, never drifting) it reads the plant, hands the
//! outputs to the [`Supervisor`], publishes the sample it returns, writes the fallback if
//! the supervisor says so, then feeds it each command that arrives until the period's own
//! command is handled or the next deadline comes, doing what each verdict says.
//!
//! With a simulated plant the simulator integrates exactly the time that passes: from `t_k`
//! to a command's arrival with the old inputs, then to `t_{k+1}` with the new ones, so the
//! network's real delay acts on the simulated rig. Plant time is the nominal schedule
//! `k h`, so a busy machine delays the loop but never distorts the plant's physics.
//!
//! Plant I/O runs on a thread of its own ([`PlantThread`]): a driver that thinks for 200 ms
//! must not stall an async worker that zenoh also needs. Whatever ends the run (its
//! duration, a stop signal, a plant that fails), the loop ends the same way: the plant
//! gets its safe stop and the run's record is returned for writing.

use std::collections::VecDeque;
use std::future::Future;
use std::time::Duration;

use mfc::trajectory::{evaluate, Piece};
use mfc::{ChannelConfig, Reference};
use protocol::{decode, encode, keys, pb, PROTOCOL_VERSION};
use serde::{Deserialize, Serialize};
use tokio::sync::{mpsc, oneshot};
use tokio::time::Instant;
use zenoh::Session;

use crate::lease::{Lease, LeaseReport};
use crate::observe::{DeviceMetrics, LoopObservers, PeriodFigures};
use crate::safety::{
    IncomingCommand, LoopMode, PeriodBegin, SafetyConfig, SafetyError, Supervisor,
    SupervisorCounters, Verdict,
};
use crate::wire::sample_flags;
use plant::progress::Progress;
use plant::record::{percentile, Accumulator, ChannelMetrics, Period, RunRecord};
use plant::scenario::{ControllerSet, Scenario, ScenarioChannel};
use plant::{Plant, PlantError};
use telemetry::Topic;

/// What the loop runs: one device on one scenario, with its local controller and its
/// safety settings.
#[derive(Debug, Clone)]
pub struct LoopConfig {
    /// Device id (key chunk).
    pub device_id: String,
    /// Number of periods to run.
    pub steps: usize,
    /// Acceptance, hold and fallback rules.
    pub safety: SafetyConfig,
    /// The local controller's channels (law and output map), also the fallback.
    pub local: Vec<ChannelConfig>,
    /// Name of the local controller set, for the summary.
    pub controller: String,
    /// The plant's channels: names, units, actuator ranges, references.
    pub channels: Vec<ScenarioChannel>,
    /// Scenario name, for the summary.
    pub scenario: String,
    /// Pause between declaring the subscriptions and the first sample, so that they reach
    /// the other peers first.
    pub startup_delay: Duration,
    /// Earlier samples sent again with each one (`Sample::previous_*`), 0 to
    /// [`protocol::RESENT_SAMPLES`]: a run of that many lost samples leaves the controller
    /// no gap, for about 25 bytes per channel and copy.
    pub resend: usize,
    /// Live progress, metrics and recording (default: none).
    pub observers: LoopObservers,
    /// Wake on the period's deadlines to about 0.1 ms ([`crate::pace`]) rather than on
    /// tokio's timer (1 to 2 ms late). Default true. Each wait borrows a thread of tokio's
    /// blocking pool for its last 1.5 ms, so a process that hosts hundreds of loops (the
    /// gateway) turns it off rather than keep a hundred threads sleeping.
    pub precise_wake: bool,
    /// The device's key (`protocol::auth`): samples go out sealed with it and a command
    /// is judged only if it opens with it. `None` runs open: no proof either way, and
    /// the log says so at start. A gateway's plants have none of their own: the gateway
    /// seals and opens their batches with its key.
    pub auth: Option<protocol::auth::Key>,
    /// The plant's safe inputs ([`plant::scenario::Scenario::safe_inputs`]): written at
    /// start and by the safe-stop fallback.
    pub safe: Vec<f64>,
}

impl LoopConfig {
    /// Run `scenario` as `device_id` with `controller` as the local copy.
    pub fn new(
        scenario: &Scenario,
        controller: &ControllerSet,
        device_id: &str,
        safety: SafetyConfig,
    ) -> Self {
        Self {
            device_id: device_id.into(),
            steps: scenario.steps(),
            safety,
            local: scenario.channel_configs(controller),
            controller: controller.name.clone(),
            channels: scenario.channels.clone(),
            scenario: scenario.name.clone(),
            startup_delay: Duration::from_millis(100),
            resend: protocol::RESENT_SAMPLES,
            observers: LoopObservers::default(),
            precise_wake: true,
            auth: None,
            safe: scenario.safe_inputs(),
        }
    }
}

/// How a run ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum End {
    /// Ran for its whole duration.
    Completed,
    /// Stopped early on request (SIGINT, SIGTERM, the caller's stop future).
    Interrupted,
    /// The plant failed (a driver that stopped answering, exited, or broke the protocol).
    PlantFailed,
}

/// Whether the plant had a controller, as an operator needs to know it: a plant that never
/// reached one is a deployment problem (endpoint, TLS, access control), one that lost it
/// is a network or service problem.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ControllerLink {
    /// No controller ever answered: the plant ran on its fallback all along.
    Never,
    /// A controller answered, then stopped, and the run ended on the fallback.
    Lost,
    /// A controller answered, and was answering (or holding) at the end.
    Kept,
}

/// How the run stood with its controller, from the mode of every period and whether any
/// controller answered: the link, and for [`ControllerLink::Lost`] the plant time at which the
/// final stretch off remote control began.
pub fn link_of(modes: &[LoopMode], times: &[f64], reached: bool) -> (ControllerLink, Option<f64>) {
    if !reached {
        return (ControllerLink::Never, None);
    }
    match modes.last() {
        Some(LoopMode::Local | LoopMode::SafeStop) => {
            let start = modes
                .iter()
                .rposition(|m| *m == LoopMode::Remote)
                .map_or(0, |k| k + 1);
            (ControllerLink::Lost, times.get(start).copied())
        }
        _ => (ControllerLink::Kept, None),
    }
}

/// What a run of the agent measured, and how it ended: `summary.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct AgentReport {
    /// Device id.
    pub device_id: String,
    /// Scenario name.
    pub scenario: String,
    /// The local controller's name.
    pub controller: String,
    /// How the run ended.
    pub end: End,
    /// Why, when it did not complete normally.
    pub error: Option<String>,
    /// Whether the plant acknowledged its safe stop at the end.
    pub safe_stop_applied: bool,
    /// Why the safe stop could not be confirmed, if it could not.
    pub safe_stop_error: Option<String>,
    /// Whether any controller answered (a command or a warm-up answer) during the run.
    pub controller_reached: bool,
    /// Never reached, lost (and ended on the fallback), or kept.
    pub link: ControllerLink,
    /// For a lost link: the plant time (s) from which the plant stayed off remote control.
    pub lost_at: Option<f64>,
    /// Tracking per channel.
    pub channels: Vec<ChannelMetrics>,
    /// What the supervisor counted: periods, commands, late, missing, stale, fallbacks...
    pub counters: SupervisorCounters,
    /// Sample-to-command round trip, µs: median.
    pub rtt_p50_us: f64,
    /// 99th percentile.
    pub rtt_p99_us: f64,
    /// Periods whose deadline the loop missed by more than half a period.
    pub overruns: u64,
    /// Plant limit hits (the AERO's pitch stop).
    pub limit_hits: usize,
    /// The plant's command lease: grants, lapses, refusals by reason, and which holder
    /// under which epoch commanded which periods.
    #[serde(default)]
    pub lease: LeaseReport,
    /// Whether the run's messages were authenticated, and the commands refused because
    /// they were not (no MAC, or one under another key: forged, altered, misdirected).
    #[serde(default)]
    pub auth: AuthReport,
}

/// Proof of origin in a run (`summary.json`'s `auth`).
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct AuthReport {
    /// Samples sealed and commands checked with the device's key (else: open).
    pub authenticated: bool,
    /// Commands refused unread: no MAC, or not this device's.
    pub forged: u64,
}

impl AgentReport {
    /// Whether the run went to its end (neither interrupted nor failed).
    pub fn completed(&self) -> bool {
        self.end == End::Completed
    }

    /// The process exit status this run deserves: 0 when it ran (or was stopped on
    /// request) with a controller answering and the safe stop applied; 3 when no
    /// controller ever answered (the plant ran on its fallback all along: a deployment
    /// problem, not a success); 5 when the controller was lost and the run ended on the
    /// fallback; 4 when the plant failed or did not confirm its safe stop.
    pub fn exit_code(&self) -> u8 {
        if self.end == End::PlantFailed || !self.safe_stop_applied {
            4
        } else {
            match self.link {
                ControllerLink::Never => 3,
                ControllerLink::Lost => 5,
                ControllerLink::Kept => 0,
            }
        }
    }

    /// One line for a terminal.
    pub fn headline(&self) -> String {
        let end = match self.end {
            End::Completed => "completed".to_string(),
            End::Interrupted => match &self.error {
                Some(why) => format!("interrupted ({why})"),
                None => "interrupted".to_string(),
            },
            End::PlantFailed => format!(
                "plant failed: {}",
                self.error.as_deref().unwrap_or("unknown")
            ),
        };
        let stop = if self.safe_stop_applied {
            "safe stop applied".to_string()
        } else {
            format!(
                "safe stop NOT confirmed ({})",
                self.safe_stop_error.as_deref().unwrap_or("unknown")
            )
        };
        let ctl = match (self.link, self.lost_at) {
            (ControllerLink::Kept, _) => String::new(),
            (ControllerLink::Never, _) if self.counters.periods == 0 => {
                "; NO CONTROLLER EVER ANSWERED (check the endpoint, TLS and access control)".into()
            }
            (ControllerLink::Never, _) => {
                "; NO CONTROLLER EVER ANSWERED (check the endpoint, TLS and \
                                 access control): the plant ran on its fallback"
                    .into()
            }
            (ControllerLink::Lost, at) => format!(
                "; CONTROLLER LOST at t = {:.2} s: the run ended on the fallback",
                at.unwrap_or(0.0)
            ),
        };
        format!(
            "{}: {end} after {} periods, {stop}{ctl}",
            self.device_id, self.counters.periods
        )
    }
}

/// A finished run: the report and the record.
#[derive(Debug, Clone)]
pub struct AgentRun {
    /// What the run measured.
    pub report: AgentReport,
    /// Period by period.
    pub record: RunRecord,
}

/// Why the loop could not start. Once it runs, nothing is an error: a failure ends the
/// run and is reported in [`AgentReport::end`], with the record so far.
#[derive(Debug, thiserror::Error)]
pub enum AgentError {
    /// The plant failed before the first period.
    #[error(transparent)]
    Plant(#[from] PlantError),
    /// Zenoh refused a declaration.
    #[error(transparent)]
    Transport(#[from] transport::TransportError),
    /// The safety settings or the local controller were refused.
    #[error(transparent)]
    Safety(#[from] SafetyError),
    /// The configuration does not fit the plant.
    #[error("{0}")]
    Config(String),
}

enum PlantRequest {
    Read,
    Write(Vec<f64>),
    Advance(f64),
    Stop,
}

type PlantReply = oneshot::Sender<Result<Vec<f64>, PlantError>>;

/// Open the plant `scenario` names (see [`fieldbus::open`]: a simulator, a driver, or a
/// server behind an industrial protocol) on a blocking thread: a driver's `hello` or a
/// server's connection may take seconds, and plant I/O never runs on an async worker.
pub async fn open_plant(scenario: &Scenario, seed: u64) -> Result<Box<dyn Plant>, PlantError> {
    let (source, n) = (scenario.plant.clone(), scenario.channels.len());
    tokio::task::spawn_blocking(move || fieldbus::open(&source, seed, n))
        .await
        .unwrap_or_else(|e| Err(PlantError::Driver(format!("opening the plant: {e}"))))
}

/// The plant on a thread of its own, driven by async calls: plant I/O may block (a driver
/// process, a serial line) and must never block an async worker.
pub struct PlantThread {
    tx: std::sync::mpsc::Sender<(PlantRequest, PlantReply)>,
    channels: usize,
    limit_hits: std::sync::Arc<std::sync::atomic::AtomicUsize>,
}

impl PlantThread {
    /// Move `plant` to a new thread. The thread ends after `stop` or when the handle is
    /// dropped (dropping a [`plant::driver::DriverPlant`] asks its driver for a safe stop).
    pub fn spawn(mut plant: Box<dyn Plant>) -> Self {
        let channels = plant.channels();
        let (tx, rx) = std::sync::mpsc::channel::<(PlantRequest, PlantReply)>();
        let limit_hits = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let hits = limit_hits.clone();
        std::thread::Builder::new()
            .name("plant-io".into())
            .spawn(move || {
                while let Ok((req, reply)) = rx.recv() {
                    let stop = matches!(req, PlantRequest::Stop);
                    let r = match req {
                        PlantRequest::Read => plant.read(),
                        PlantRequest::Write(v) => plant.write(&v),
                        PlantRequest::Advance(dt) => plant.advance(dt).map(|()| Vec::new()),
                        PlantRequest::Stop => plant.stop().map(|()| Vec::new()),
                    };
                    hits.store(plant.limit_hits(), std::sync::atomic::Ordering::Relaxed);
                    let _ = reply.send(r);
                    if stop {
                        break;
                    }
                }
            })
            .expect("spawning a thread");
        Self {
            tx,
            channels,
            limit_hits,
        }
    }

    async fn call(&self, req: PlantRequest) -> Result<Vec<f64>, PlantError> {
        let (reply, answer) = oneshot::channel();
        self.tx
            .send((req, reply))
            .map_err(|_| PlantError::Driver("the plant thread has ended".into()))?;
        answer
            .await
            .map_err(|_| PlantError::Driver("the plant thread has ended".into()))?
    }

    /// Measure the outputs.
    pub async fn read(&self) -> Result<Vec<f64>, PlantError> {
        self.call(PlantRequest::Read).await
    }
    /// Apply `v`; returns what was really applied.
    pub async fn write(&self, v: Vec<f64>) -> Result<Vec<f64>, PlantError> {
        self.call(PlantRequest::Write(v)).await
    }
    /// Let `dt` seconds of plant time pass.
    pub async fn advance(&self, dt: f64) -> Result<(), PlantError> {
        self.call(PlantRequest::Advance(dt)).await.map(|_| ())
    }
    /// The safe stop; the thread ends after it.
    pub async fn stop(&self) -> Result<(), PlantError> {
        self.call(PlantRequest::Stop).await.map(|_| ())
    }
    /// Number of channels.
    pub fn channels(&self) -> usize {
        self.channels
    }
    /// The plant's limit hits so far.
    pub fn limit_hits(&self) -> usize {
        self.limit_hits.load(std::sync::atomic::Ordering::Relaxed)
    }
}

/// Counts a noisy event and says when to log it: the first few, then every thousandth,
/// so a flood of garbage cannot flood the log.
#[derive(Default)]
struct LogBudget(u64);

impl LogBudget {
    fn hit(&mut self) -> bool {
        self.0 += 1;
        self.0 <= 5 || self.0 % 1000 == 0
    }
}

/// The report and (empty) record of a run stopped before it could start: the plant was
/// opened and got its safe stop (`stopped` says how that went), but no session ever opened,
/// so no period ran and no controller was reached. Written like any other record, so that
/// whoever looks at the device's directory sees what happened.
pub fn never_started(config: &LoopConfig, stopped: Result<(), PlantError>) -> AgentRun {
    let names: Vec<String> = config.channels.iter().map(|c| c.name.clone()).collect();
    let units = config.channels.iter().map(|c| c.unit.clone()).collect();
    let report = AgentReport {
        device_id: config.device_id.clone(),
        scenario: config.scenario.clone(),
        controller: config.controller.clone(),
        end: End::Interrupted,
        error: Some("stopped while waiting for the router: no session, no period ran".into()),
        safe_stop_applied: stopped.is_ok(),
        safe_stop_error: stopped.err().map(|e| e.to_string()),
        controller_reached: false,
        link: ControllerLink::Never,
        lost_at: None,
        channels: names
            .iter()
            .map(|n| Accumulator::default().finish(n))
            .collect(),
        counters: SupervisorCounters::default(),
        rtt_p50_us: 0.0,
        rtt_p99_us: 0.0,
        overruns: 0,
        limit_hits: 0,
        lease: LeaseReport::default(),
        auth: AuthReport::default(),
    };
    AgentRun {
        report,
        record: RunRecord::new(names, units, 0),
    }
}

/// Run the loop for `config.steps` periods on `session`, or until `stop` resolves or the
/// plant fails; then apply the plant's safe stop. Returns the report and the record.
pub async fn run_loop(
    session: &Session,
    plant: Box<dyn Plant>,
    config: &LoopConfig,
    run_id: u64,
    stop: impl Future<Output = ()>,
) -> Result<AgentRun, AgentError> {
    let plant = PlantThread::spawn(plant);
    match declare_and_run(session, &plant, config, run_id, stop).await {
        Ok(run) => Ok(run),
        Err(e) => {
            // Whatever failed before the loop started, the plant still gets its safe stop.
            if let Err(stop_err) = plant.stop().await {
                tracing::error!(device = %config.device_id, "safe stop failed: {stop_err}");
            }
            Err(e)
        }
    }
}

async fn declare_and_run(
    session: &Session,
    plant: &PlantThread,
    config: &LoopConfig,
    run_id: u64,
    stop: impl Future<Output = ()>,
) -> Result<AgentRun, AgentError> {
    let n = plant.channels();
    check_loop(config, n)?;
    let id = config.device_id.as_str();
    if config.auth.is_some() {
        tracing::info!(device = id, "auth: keys (samples sealed, commands checked)");
    } else {
        tracing::warn!(
            device = id,
            "auth: open (no key_file): any peer that may put on this device's command key \
             can command it"
        );
    }

    let (tx, rx) = mpsc::channel::<(Instant, Vec<u8>)>(256);
    let _commands = session
        .declare_subscriber(keys::command(id))
        .callback(move |s| {
            // Never block zenoh's receive thread: a full queue drops the newest, and the
            // supervisor treats that like a lost command.
            let _ = tx.try_send((Instant::now(), s.payload().to_bytes().into_owned()));
        })
        .await
        .map_err(|e| transport::TransportError::Declare {
            what: format!("subscriber {}", keys::command(id)),
            reason: e.to_string(),
        })?;
    let publisher = transport::control_publisher(session, keys::shard_sample(id)).await?;
    let _token = declare_alive(session, id).await?;
    let supervisor = start_supervisor(plant, config, run_id).await?;
    let out = SampleOut::Own(&publisher);
    Ok(periods(plant, config, supervisor, rx, &out, run_id, stop).await)
}

/// The plant's safe inputs written, and a supervisor that starts from what it applied,
/// falls back to those inputs and grants run `run_id`'s lease.
async fn start_supervisor(
    plant: &PlantThread,
    config: &LoopConfig,
    run_id: u64,
) -> Result<Supervisor, AgentError> {
    let initial = plant.write(config.safe.clone()).await?;
    let mut supervisor = Supervisor::new(config.safety, &config.local, initial)?;
    supervisor.set_safe_inputs(config.safe.clone())?;
    supervisor.grant_leases(run_id);
    Ok(supervisor)
}

/// The checks before a loop starts: channel counts agree, safety settings and id are valid.
fn check_loop(config: &LoopConfig, n: usize) -> Result<(), AgentError> {
    if config.local.len() != n || config.channels.len() != n {
        return Err(AgentError::Config(format!(
            "{}: the plant has {n} channel(s), the local controller {} and the scenario {}",
            config.device_id,
            config.local.len(),
            config.channels.len()
        )));
    }
    config.safety.validate()?;
    protocol::keys::check_id(&config.device_id).map_err(|e| AgentError::Config(e.to_string()))?;
    Ok(())
}

/// The plant's liveliness token (`mfc/v1/alive/plant/{id}`), held while its loop runs.
async fn declare_alive(
    session: &Session,
    id: &str,
) -> Result<zenoh::liveliness::LivelinessToken, AgentError> {
    Ok(session
        .liveliness()
        .declare_token(keys::alive_plant(id))
        .await
        .map_err(|e| transport::TransportError::Declare {
            what: "liveliness token".into(),
            reason: e.to_string(),
        })?)
}

/// Where a loop's samples go: its own key, or its gateway's batch.
pub enum SampleOut<'a> {
    /// A single-rig agent: each sample on the device's shard key.
    Own(&'a zenoh::pubsub::Publisher<'a>),
    /// A plant hosted by a gateway ([`crate::gateway`]): the gateway sends it with the
    /// samples of its other plants, in one batch per period.
    Gateway(mpsc::Sender<pb::Sample>),
}

impl SampleOut<'_> {
    /// Send `sample`, sealed with `key` on its own key (a gateway seals the batch).
    async fn send(
        &self,
        sample: pb::Sample,
        key: Option<&protocol::auth::Key>,
    ) -> Result<(), String> {
        match self {
            SampleOut::Own(p) => {
                let bytes = encode(&sample);
                let bytes = match key {
                    Some(k) => k.seal(protocol::auth::Kind::Sample, bytes),
                    None => bytes,
                };
                p.put(bytes).await.map_err(|e| e.to_string())
            }
            // Never wait on the batcher: a full queue is a lost sample, as on the network.
            SampleOut::Gateway(tx) => tx.try_send(sample).map_err(|e| e.to_string()),
        }
    }
}

/// Run one plant hosted by a gateway: the same loop and the same safety as a single-rig
/// agent ([`run_loop`]), with its samples handed to the gateway's batcher and its commands
/// taken from the gateway's dispatcher instead of keys of its own.
pub async fn run_hosted(
    session: &Session,
    plant: Box<dyn Plant>,
    config: &LoopConfig,
    run_id: u64,
    stop: impl Future<Output = ()>,
    samples: mpsc::Sender<pb::Sample>,
    commands: mpsc::Receiver<(Instant, Vec<u8>)>,
) -> Result<AgentRun, AgentError> {
    let plant = PlantThread::spawn(plant);
    let started = async {
        let n = plant.channels();
        check_loop(config, n)?;
        // Each hosted plant announces itself as a single rig would.
        let token = declare_alive(session, &config.device_id).await?;
        let supervisor = start_supervisor(&plant, config, run_id).await?;
        Ok((token, supervisor))
    }
    .await;
    match started {
        Ok((_token, supervisor)) => {
            let out = SampleOut::Gateway(samples);
            Ok(periods(&plant, config, supervisor, commands, &out, run_id, stop).await)
        }
        Err(e) => {
            if let Err(stop_err) = plant.stop().await {
                tracing::error!(device = %config.device_id, "safe stop failed: {stop_err}");
            }
            Err(e)
        }
    }
}

/// The periodic part. Never fails: whatever happens ends the run with a report.
async fn periods(
    plant: &PlantThread,
    config: &LoopConfig,
    sup: Supervisor,
    rx: mpsc::Receiver<(Instant, Vec<u8>)>,
    publisher: &SampleOut<'_>,
    run_id: u64,
    stop: impl Future<Output = ()>,
) -> AgentRun {
    let mut run = PeriodLoop::new(plant, config, sup, rx, publisher, run_id);
    tokio::pin!(stop);
    let ended = run.all_periods(stop.as_mut()).await.err().unwrap_or(Ended {
        end: End::Completed,
        error: None,
    });
    run.finish(ended).await
}

/// Why the periods stopped before the last: interrupted, or the plant (or the wiring)
/// failed, and what went wrong.
struct Ended {
    end: End,
    error: Option<String>,
}

impl Ended {
    const INTERRUPTED: Self = Self {
        end: End::Interrupted,
        error: None,
    };

    fn plant_failed(error: impl std::fmt::Display) -> Self {
        Self {
            end: End::PlantFailed,
            error: Some(error.to_string()),
        }
    }
}

/// One period as it goes: what the deadline measured and what the commands brought.
struct OpenPeriod {
    k: usize,
    /// Plant time `k h`.
    t: f64,
    deadline: Instant,
    y: Vec<f64>,
    /// The mode before this period's decisions.
    mode_before: LoopMode,
    /// The round trip of the command applied in this period (µs; 0: none).
    rtt_us: u32,
    /// The applied command's `u` and `F` estimates.
    remote: Option<(Vec<f64>, Vec<f64>)>,
}

/// The loop's state between periods, with one method per event: a deadline
/// ([`PeriodLoop::on_deadline`]), a command ([`PeriodLoop::on_command`]), the period's end
/// ([`PeriodLoop::on_period_end`]), and the run's end ([`PeriodLoop::finish`]).
struct PeriodLoop<'a, 'p> {
    plant: &'a PlantThread,
    config: &'a LoopConfig,
    sup: Supervisor,
    rx: mpsc::Receiver<(Instant, Vec<u8>)>,
    out: &'a SampleOut<'p>,
    run_id: u64,
    /// Each channel's reference pieces.
    references: Vec<&'a [Piece]>,
    refs: Vec<Reference>,
    record: RunRecord,
    acc: Vec<Accumulator>,
    rtts: Vec<u32>,
    /// When each recent sample was sent, for the round trip of its command.
    sent_at: VecDeque<(u64, Instant)>,
    last_rtt_us: u32,
    /// The last samples' times, outputs and applied, newest first, sent again with the
    /// next one (`pb::Sample::previous_plant_time`).
    previous: VecDeque<(f64, Vec<f64>, Vec<f64>)>,
    overruns: u64,
    bad_commands: LogBudget,
    refusals: LogBudget,
    /// Commands refused for their MAC ([`AuthReport::forged`]).
    forged: u64,
    metrics: Option<DeviceMetrics>,
    /// The last F estimates received, for the metrics.
    last_f: Option<Vec<f64>>,
}

impl<'a, 'p> PeriodLoop<'a, 'p> {
    fn new(
        plant: &'a PlantThread,
        config: &'a LoopConfig,
        sup: Supervisor,
        rx: mpsc::Receiver<(Instant, Vec<u8>)>,
        out: &'a SampleOut<'p>,
        run_id: u64,
    ) -> Self {
        let n = plant.channels();
        let channels = &config.channels;
        Self {
            plant,
            config,
            sup,
            rx,
            out,
            run_id,
            references: channels.iter().map(|c| c.reference.as_slice()).collect(),
            refs: vec![Reference::default(); n],
            record: RunRecord::new(
                channels.iter().map(|c| c.name.clone()).collect(),
                channels.iter().map(|c| c.unit.clone()).collect(),
                config.steps,
            ),
            acc: vec![Accumulator::default(); n],
            rtts: Vec::with_capacity(config.steps),
            sent_at: VecDeque::new(),
            last_rtt_us: 0,
            previous: VecDeque::with_capacity(protocol::RESENT_SAMPLES),
            overruns: 0,
            bad_commands: LogBudget::default(),
            refusals: LogBudget::default(),
            forged: 0,
            metrics: config
                .observers
                .metrics
                .as_ref()
                .map(|m| m.device(&config.device_id, n)),
            last_f: None,
        }
    }

    fn id(&self) -> &'a str {
        self.config.device_id.as_str()
    }

    fn mcap(&self) -> Option<&'a telemetry::Recording> {
        self.config.observers.recording.as_ref()
    }

    /// Every period until the last, or until `stop` or a failure ends them early.
    async fn all_periods(
        &mut self,
        mut stop: std::pin::Pin<&mut impl Future<Output = ()>>,
    ) -> Result<(), Ended> {
        let (config, h) = (self.config, self.config.safety.period);
        let period = Duration::from_secs_f64(h);
        if let Some(r) = self.mcap() {
            let what = format!("run {:#x}: {} periods of {h} s", self.run_id, config.steps);
            r.event(self.id(), "start", what, 0.0);
        }
        tokio::select! {
            _ = tokio::time::sleep(config.startup_delay) => {}
            _ = stop.as_mut() => return Err(Ended::INTERRUPTED),
        }
        let start = Instant::now();
        for k in 0..config.steps {
            let deadline = start + period * k as u32;
            tokio::select! {
                _ = crate::pace::wait_until(deadline, config.precise_wake) => {}
                _ = stop.as_mut() => return Err(Ended::INTERRUPTED),
            }
            let mut p = self.on_deadline(k, deadline).await?;
            // One timer for the whole period, so that a command's arrival does not
            // restart it.
            let period_end = crate::pace::wait_until(deadline + period, config.precise_wake);
            tokio::pin!(period_end);
            loop {
                let arrived = tokio::select! {
                    r = self.rx.recv() => r,
                    () = &mut period_end => None,
                    _ = stop.as_mut() => return Err(Ended::INTERRUPTED),
                };
                let Some((arrival, bytes)) = arrived else {
                    break;
                };
                if self.on_command(&mut p, arrival, bytes).await? {
                    break;
                }
            }
            self.on_period_end(p).await?;
        }
        Ok(())
    }

    /// A deadline: read the plant, begin the period, publish its sample, and write what
    /// the supervisor says to write at the start (the fallback, or a horizon's element).
    async fn on_deadline(&mut self, k: usize, deadline: Instant) -> Result<OpenPeriod, Ended> {
        let h = self.config.safety.period;
        if Instant::now() > deadline + Duration::from_secs_f64(h) / 2 {
            self.overruns += 1;
        }
        let t = k as f64 * h;
        let y = self.plant.read().await.map_err(Ended::plant_failed)?;
        for (r, pieces) in self.refs.iter_mut().zip(&self.references) {
            *r = evaluate(pieces, t);
        }
        let mode_before = self.sup.mode();
        let begin = self
            .sup
            .begin_period(k as u64, t, &y, &self.refs)
            .map_err(|e| Ended::plant_failed(format!("supervisor: {e}")))?;
        self.publish(k, t, &y, &begin).await;
        let answered_once = {
            let c = self.sup.counters();
            c.commands + c.warming_up > 0
        };
        // "Never connected" is said every 5 s of plant time until a controller answers.
        let never_every = ((5.0 / h).round() as usize).max(1);
        if !answered_once && k > 0 && k % never_every == 0 {
            tracing::warn!(
                device = self.id(),
                "no controller has answered after {:.0} s: check the endpoint, TLS and access \
                 control (the plant runs on its {:?})",
                t,
                self.sup.mode()
            );
        }
        if let Some(v) = begin.write {
            // A write at the start of a period is the fallback engaging, or (in Remote or
            // Holding) the last command's horizon playing its element: only the first is
            // news.
            if self.sup.mode().is_fallback() && !mode_before.is_fallback() {
                self.warn_fallback(k, answered_once);
            }
            let a = self.plant.write(v).await.map_err(Ended::plant_failed)?;
            self.sup.applied(&a);
        }
        Ok(OpenPeriod {
            k,
            t,
            deadline,
            y,
            mode_before,
            rtt_us: 0,
            remote: None,
        })
    }

    /// Sample `k` out, with the earlier ones it carries again, and into the recording.
    async fn publish(&mut self, k: usize, t: f64, y: &[f64], begin: &PeriodBegin) {
        let config = self.config;
        let (lease_flag, lease_holder, lease_instance, lease_epoch, lease_refused) =
            match self.sup.lease() {
                Some(l) => (
                    pb::SampleFlags::Lease as u32,
                    l.holder().unwrap_or_default().to_string(),
                    l.instance(),
                    l.epoch(),
                    l.counters().refused(),
                ),
                None => (0, String::new(), 0, 0, 0),
            };
        let sample = pb::Sample {
            version: PROTOCOL_VERSION,
            device_id: config.device_id.clone(),
            seq: k as u64,
            plant_time: t,
            outputs: y.to_vec(),
            applied: begin.applied_mean.clone(),
            flags: sample_flags(begin.sample_mode) | lease_flag,
            lease_holder,
            lease_instance,
            lease_epoch,
            lease_refused,
            sent_unix_ns: protocol::unix_ns(),
            last_rtt_us: self.last_rtt_us,
            run_id: self.run_id,
            previous_plant_time: self.previous.iter().map(|p| p.0).collect(),
            previous_outputs: self
                .previous
                .iter()
                .flat_map(|p| p.1.iter().copied())
                .collect(),
            previous_applied: self
                .previous
                .iter()
                .flat_map(|p| p.2.iter().copied())
                .collect(),
            // Appended by the seal, over the bytes before it.
            mac: Vec::new(),
        };
        self.previous
            .push_front((t, y.to_vec(), begin.applied_mean.clone()));
        self.previous
            .truncate(config.resend.min(protocol::RESENT_SAMPLES));
        self.sent_at.push_back((k as u64, Instant::now()));
        if self.sent_at.len() > config.safety.max_age as usize + 2 {
            self.sent_at.pop_front();
        }
        if let Some(r) = self.mcap() {
            let at = sample.sent_unix_ns;
            r.record(self.id(), Topic::Sample, at, at, encode(&sample));
        }
        if let Err(e) = self.out.send(sample, config.auth.as_ref()).await {
            tracing::warn!(device = self.id(), "publishing sample {k}: {e}");
        }
    }

    fn warn_fallback(&self, k: usize, answered_once: bool) {
        let (id, streak, mode) = (self.id(), self.sup.missing_streak(), self.sup.mode());
        if answered_once {
            tracing::warn!(
                device = id,
                seq = k,
                "controller lost: no command for {streak} periods, now {mode:?}"
            );
        } else {
            tracing::warn!(
                device = id,
                seq = k,
                "no controller yet: {mode:?} after {streak} periods"
            );
        }
    }

    /// A command arrived: decode it, let the supervisor judge it, and do what it says.
    /// Returns whether the period's own command has been handled (no need to wait for
    /// more).
    async fn on_command(
        &mut self,
        p: &mut OpenPeriod,
        arrival: Instant,
        bytes: Vec<u8>,
    ) -> Result<bool, Ended> {
        let id = self.id();
        let body = match &self.config.auth {
            Some(key) => match key.open(protocol::auth::Kind::Command, &bytes) {
                Ok(body) => body,
                Err(e) => {
                    self.forged += 1;
                    if self.bad_commands.hit() {
                        tracing::warn!(device = id, "command refused unread: {e}");
                    }
                    return Ok(false);
                }
            },
            None => &bytes,
        };
        let cmd = match decode::<pb::Command>(body) {
            Ok(c) if c.device_id == id => c,
            Ok(_) => return Ok(false),
            Err(e) => {
                if self.bad_commands.hit() {
                    tracing::warn!(device = id, "undecodable command: {e}");
                }
                return Ok(false);
            }
        };
        if let Some(r) = self.mcap() {
            r.record(
                id,
                Topic::Command,
                protocol::unix_ns(),
                cmd.controller_unix_ns,
                bytes,
            );
        }
        let at = arrival.saturating_duration_since(p.deadline).as_secs_f64();
        let was = self.sup.mode();
        let (verdict, answered) = self.sup.on_command(at, IncomingCommand::from_wire(&cmd));
        match verdict {
            Verdict::Apply { v, advance, .. } => {
                let written = match self.plant.advance(advance).await {
                    Ok(()) => self.plant.write(v).await,
                    Err(e) => Err(e),
                };
                let a = written.map_err(Ended::plant_failed)?;
                self.sup.applied(&a);
                if let Some((_, sent)) = self.sent_at.iter().find(|(q, _)| *q == cmd.seq) {
                    p.rtt_us = u32::try_from(arrival.saturating_duration_since(*sent).as_micros())
                        .unwrap_or(u32::MAX);
                    self.rtts.push(p.rtt_us);
                }
                if matches!(was, LoopMode::Local | LoopMode::SafeStop) {
                    tracing::info!(
                        device = id,
                        seq = p.k,
                        "commands are back: remote control resumes"
                    );
                }
                p.remote = Some((cmd.u, cmd.f_est));
            }
            Verdict::Rejected => {
                if self.refusals.hit() {
                    tracing::warn!(
                        device = id,
                        seq = cmd.seq,
                        "sample refused by the controller: {}",
                        cmd.error
                    );
                }
            }
            Verdict::WarmingUp | Verdict::Ignored(_) => {}
        }
        Ok(answered)
    }

    /// The period's end: the supervisor closes it, the plant's time moves on, and the
    /// period goes into the metrics, the progress board and the record.
    async fn on_period_end(&mut self, p: OpenPeriod) -> Result<(), Ended> {
        let (id, h) = (self.id(), self.config.safety.period);
        let done = self
            .sup
            .end_period()
            .map_err(|e| Ended::plant_failed(format!("supervisor: {e}")))?;
        self.plant
            .advance(done.advance)
            .await
            .map_err(Ended::plant_failed)?;
        self.last_rtt_us = p.rtt_us;
        let applied = self.sup.applied_now().to_vec();
        for (i, c) in self.config.channels.iter().enumerate() {
            let e = p.y[i] - self.refs[i].y;
            self.acc[i].add(e, h, applied[i], c.saturated(applied[i]));
        }
        if let (Some(r), true) = (&p.remote, self.metrics.is_some()) {
            self.last_f = Some(r.1.clone());
        }
        if let (Some(r), true) = (self.mcap(), done.mode != p.mode_before) {
            let change = format!("{:?} -> {:?}", p.mode_before, done.mode);
            r.event(id, "mode", change, p.t);
        }
        if let Some(d) = &self.metrics {
            d.period(&PeriodFigures {
                counters: self.sup.counters(),
                rtt_us: p.rtt_us,
                mode: done.mode,
                f_est: self.last_f.as_deref(),
                queue: self.rx.len(),
                overruns: self.overruns,
            });
        }
        // The board is refreshed ten times a second of plant time: enough for a person.
        let board_every = ((0.1 / h).round() as usize).max(1);
        if let (Some(b), true) = (&self.config.observers.progress, p.k % board_every == 0) {
            b.update(self.progress(p.t, p.rtt_us, done.mode, false));
        }
        let y_ref: Vec<f64> = self.refs.iter().map(|r| r.y).collect();
        self.record.push(Period {
            t: p.t,
            y_ref: &y_ref,
            y: &p.y,
            u: p.remote.as_ref().map(|r| r.0.as_slice()),
            v: &applied,
            f_est: p.remote.as_ref().map(|r| r.1.as_slice()),
            net: Some((done.mode, p.rtt_us)),
        });
        Ok(())
    }

    /// A plant's line on the progress board.
    fn progress(&self, t: f64, rtt_us: u32, mode: LoopMode, done: bool) -> Progress {
        let counters = self.sup.counters();
        Progress {
            device: self.config.device_id.clone(),
            t,
            duration: self.config.steps as f64 * self.config.safety.period,
            rms: self
                .acc
                .iter()
                .zip(&self.config.channels)
                .map(|(a, c)| a.finish(&c.name).rms)
                .collect(),
            rtt_us,
            mode,
            fallbacks: counters.fallbacks,
            missing: counters.missing,
            done,
        }
    }

    /// However the run ended, the plant gets its safe stop; then the report.
    async fn finish(mut self, Ended { end, error }: Ended) -> AgentRun {
        let id = self.id();
        let (safe_stop_applied, safe_stop_error) = match self.plant.stop().await {
            Ok(()) => (true, None),
            Err(e) => {
                tracing::error!(device = id, "safe stop not confirmed: {e}");
                (false, Some(e.to_string()))
            }
        };
        if let Some(e) = &error {
            tracing::error!(device = id, "run ended: {e}");
        }
        if let Some(b) = &self.config.observers.progress {
            let t = self.record.t.last().copied().unwrap_or(0.0);
            b.update(self.progress(t, self.last_rtt_us, self.sup.mode(), true));
        }
        if let Some(r) = self.mcap() {
            let why = error.as_ref().map(|e| format!(": {e}")).unwrap_or_default();
            r.event(id, "end", format!("{end:?}{why}"), 0.0);
        }
        self.rtts.sort_unstable();
        let counters = self.sup.counters().clone();
        let reached = counters.commands + counters.warming_up > 0;
        let (link, lost_at) = link_of(&self.record.modes, &self.record.t, reached);
        let report = AgentReport {
            device_id: id.to_string(),
            scenario: self.config.scenario.clone(),
            controller: self.config.controller.clone(),
            end,
            error,
            safe_stop_applied,
            safe_stop_error,
            controller_reached: reached,
            link,
            lost_at,
            channels: self
                .acc
                .iter()
                .zip(&self.config.channels)
                .map(|(a, c)| a.finish(&c.name))
                .collect(),
            counters,
            rtt_p50_us: percentile(&self.rtts, 0.5),
            rtt_p99_us: percentile(&self.rtts, 0.99),
            overruns: self.overruns,
            limit_hits: self.plant.limit_hits(),
            lease: self.sup.lease().map(Lease::report).unwrap_or_default(),
            auth: AuthReport {
                authenticated: self.config.auth.is_some(),
                forged: self.forged,
            },
        };
        AgentRun {
            report,
            record: self.record,
        }
    }
}

#[cfg(test)]
mod link_tests {
    use super::*;

    #[test]
    fn never_lost_and_kept_are_told_apart() {
        use LoopMode::*;
        let t: Vec<f64> = (0..8).map(|k| k as f64 * 0.01).collect();
        assert_eq!(
            link_of(&[Local; 8], &t, false),
            (ControllerLink::Never, None)
        );
        let lost = [
            Remote, Remote, Remote, Holding, Holding, Local, Local, Local,
        ];
        assert_eq!(link_of(&lost, &t, true), (ControllerLink::Lost, Some(0.03)));
        // Lost, then back: kept. Holding at the very end is not a loss either.
        let back = [
            Remote, Holding, Local, Local, Remote, Remote, Remote, Holding,
        ];
        assert_eq!(link_of(&back, &t, true), (ControllerLink::Kept, None));
        // A warm-up answer counts as reached, even if no command was ever applied.
        assert_eq!(
            link_of(&[Local; 8], &t, true),
            (ControllerLink::Lost, Some(0.0))
        );
        assert_eq!(
            link_of(&[Remote, SafeStop], &t, true),
            (ControllerLink::Lost, Some(0.01))
        );
    }
}

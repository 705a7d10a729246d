//! The worker's start and its loop: restore, declare, join, then wait for whatever comes
//! next and hand each event to its one handler ([`super::requests`] for operators'
//! queries, [`super::operators`] for the audit file's word on a change,
//! [`super::handover`] for the fleet and the hot standby).

use std::sync::Arc;
use std::time::{Duration, Instant};

use protocol::{keys, pb};
use tokio::sync::{mpsc, Notify};
use tokio::time::{interval, Interval, MissedTickBehavior};
use zenoh::Session;

use super::change::Changes;
use super::core::{publish, publish_batch, Core, Masks, Shared, Watch};
use super::drops::Drops;
use super::gate::Gate;
use super::intake::{Intake, Msg};
use super::keyring::Keyring;
use super::locks::lock;
use super::log::{Warnings, LOG_INTERVAL};
use super::routes::{
    declare_err, FleetRoutes, Routes, ServiceError, ShardRoutes, StandbyRoutes, Twins,
};
use super::worker::{Member, Worker};
use crate::config::{FleetSpec, SnapshotSpec};
use crate::fleet::{Fleet, FleetTiming, ShardAction};
use crate::inbox::Inbox;
use crate::observe::{Observers, ScrapeRequest};
use crate::standby::HotStandby;
use crate::trail::{Written, WAITING};
use crate::Registry;

/// Depth of the request queue (messages); when it is full new requests are dropped and
/// counted as `queue_full`.
const QUEUE: usize = 1024;
/// Depth of the heartbeat queue.
const HEARTBEATS: usize = 64;
/// Pending samples of devices not served (yet) share this many inbox slots.
const OTHERS: usize = 64;
/// Samples the worker serves before it looks at its other inputs again, so requests and
/// heartbeats are never starved by a busy fleet.
const BATCH: usize = 64;
/// Gateways whose batches may wait at once (each at most one batch's bytes in all,
/// `crate::inbox::Parts`): a flood of new gateway ids fills these and is dropped as
/// `queue_full`, never growing the service.
const GATEWAYS_PENDING: usize = 256;
/// Gateway batches the worker serves per turn (each may hold thousands of samples); it
/// finishes a gateway's parts once it began them, so a turn may serve up to
/// `crate::inbox::PARTS - 1` more.
const GATEWAY_TURN: usize = 4;
/// How often a fleet member looks at its releases and unanswered requests.
const FLEET_TICK: Duration = Duration::from_millis(20);

/// What the worker waits on besides its own fields.
pub(super) struct Inputs {
    rx: mpsc::Receiver<Msg>,
    /// The audit file's writer's word on this worker's records.
    written: mpsc::Receiver<Written>,
    heartbeats: mpsc::Receiver<Vec<u8>>,
    scrapes: Option<mpsc::Receiver<ScrapeRequest>>,
    heartbeat_tick: Interval,
    snapshot_tick: Interval,
    report_tick: Interval,
    fleet_tick: Interval,
}

fn ticker(period: Duration) -> Interval {
    let mut t = interval(period);
    t.set_missed_tick_behavior(MissedTickBehavior::Skip);
    t
}

impl Worker {
    /// Restore the snapshots, declare everything, join the fleet or the standby group if
    /// the file says so, and announce the service.
    pub(super) async fn start(
        session: Session,
        mut registry: Registry,
        observers: Observers,
    ) -> Result<(Self, Inputs), ServiceError> {
        let started = Instant::now();
        let id = registry.controller_id().to_string();
        let instance = registry.instance();
        let snapshots = registry.snapshot_spec().cloned();
        if let Some(sn) = &snapshots {
            restore_snapshots(&mut registry, sn, &observers);
        }
        let (fleet_spec, standby_spec) = (registry.fleet().cloned(), registry.standby().cloned());
        let watch = Watch::of(&registry, &observers);
        let (tx, rx) = mpsc::channel::<Msg>(QUEUE);
        let (hb_tx, hb_rx) = mpsc::channel::<Vec<u8>>(HEARTBEATS);
        let (written_tx, written_rx) = mpsc::channel(WAITING);
        let templates = registry.template_patterns();
        let keys = Keyring::of(&registry);
        let gate = Gate::of(&registry, observers.audit.clone());
        let mut inbox = Inbox::<pb::Sample>::new(OTHERS);
        for d in registry.device_ids() {
            inbox.serve(d);
        }
        let shared = Arc::new(Shared {
            core: std::sync::Mutex::new(Core::new(registry, watch, keys.clone(), gate)),
            inbox: std::sync::Mutex::new(inbox),
            gateways: std::sync::Mutex::new(Inbox::new(GATEWAYS_PENDING)),
            // Nothing answered until the roles are known (`sync_masks` below).
            masks: Masks::new(if fleet_spec.is_some() { 0 } else { u64::MAX }, 0),
            drops: Drops::default(),
            keys,
            wake: Notify::new(),
            twins: std::sync::Mutex::default(),
        });
        let intake = Arc::new(Intake {
            shared: shared.clone(),
            tx: tx.clone(),
            heartbeats: hb_tx,
            templates,
            session: session.clone(),
        });
        let routes = Routes::declare(&session, &intake, &id, fleet_spec.is_some()).await?;
        let (fleet_routes, member, actions) = match &fleet_spec {
            Some(spec) => {
                let (routes, member, actions) = join_fleet(&session, &intake, &id, spec).await?;
                (Some(routes), Some(member), actions)
            }
            None => (None, None, Vec::new()),
        };
        let standby_routes = match &standby_spec {
            Some(sb) => Some(StandbyRoutes::declare(&session, &intake, &sb.group).await?),
            None => None,
        };
        let twins = Twins::declare(&session, &shared, (&id, instance)).await?;
        let token = session
            .liveliness()
            .declare_token(keys::alive_controller(&id))
            .await
            .map_err(declare_err("liveliness token"))?;
        let standby = HotStandby::new(standby_spec.as_ref(), Instant::now());
        let inputs = Inputs {
            rx,
            written: written_rx,
            heartbeats: hb_rx,
            scrapes: observers.metrics.as_ref().map(|m| m.join()),
            heartbeat_tick: ticker(standby.heartbeat),
            snapshot_tick: ticker(Duration::from_millis(
                snapshots.as_ref().map_or(3_600_000, |s| s.interval_ms),
            )),
            report_tick: ticker(LOG_INTERVAL),
            fleet_tick: ticker(FLEET_TICK),
        };
        let mut worker = Self {
            _token: token,
            _twins: twins,
            standby_routes,
            _routes: routes,
            _fleet_routes: fleet_routes,
            shard_routes: ShardRoutes::default(),
            id,
            session,
            shared,
            intake,
            tx,
            member,
            standby,
            changes: Changes::new(written_tx),
            snapshots,
            warn: Warnings::default(),
            reported: [0; 8],
            started,
        };
        tracing::info!(controller = %worker.id, devices = lock(&worker.shared.core).registry.device_count(), "serving");
        worker.apply_fleet(actions).await;
        if let Some(m) = &worker.member {
            let f = &m.fleet;
            tracing::info!(controller = %worker.id, owned = f.answer_mask().count_ones(), stepped = f.step_mask().count_ones(), "fleet shards at start");
        }
        Ok((worker, inputs))
    }

    /// Serve until `shutdown` resolves or the queue closes; then save the snapshots and
    /// undeclare everything (by dropping `self`).
    pub(super) async fn run(
        mut self,
        mut inputs: Inputs,
        shutdown: impl std::future::Future<Output = ()>,
    ) {
        tokio::pin!(shutdown);
        loop {
            tokio::select! {
                () = self.shared.wake.notified() => self.serve_waiting().await,
                Some(reply) = next_scrape(&mut inputs.scrapes) => self.handle_scrape(reply),
                m = inputs.rx.recv() => match m {
                    Some(m) => self.handle(m).await,
                    None => break,
                },
                Some(bytes) = inputs.heartbeats.recv() => self.handle_heartbeat(&bytes),
                Some(w) = inputs.written.recv() => self.handle_written(w).await,
                _ = inputs.heartbeat_tick.tick(), if self.standby_routes.is_some() => {
                    self.on_heartbeat_tick().await;
                }
                _ = inputs.snapshot_tick.tick(), if self.snapshots.is_some() => self.save_snapshots(),
                _ = inputs.report_tick.tick() => self.report_drops(),
                _ = inputs.fleet_tick.tick(), if self.member.is_some() => self.on_fleet_tick().await,
                () = &mut shutdown => break,
            }
        }
        tracing::info!(controller = %self.id, "shutting down");
        self.save_snapshots();
        lock(&self.shared.core).undeclare_publishers();
    }

    /// One handler per message.
    async fn handle(&mut self, msg: Msg) {
        match msg {
            Msg::Refused {
                dev,
                sample,
                reason,
            } => self.handle_refused(&dev, &sample, reason).await,
            Msg::Reference(dev, bytes, who) => {
                self.handle_reference_put(&dev, &bytes, who.as_deref())
                    .await;
            }
            Msg::Config(q) => self.handle_config(q).await,
            Msg::Envelope(q) => self.handle_envelope(q).await,
            Msg::ReferenceQuery(q) => self.handle_reference_query(q).await,
            Msg::Status(q) => self.handle_status(q).await,
            Msg::Audit(q) => self.handle_audit(q).await,
            Msg::Commission(q) => self.handle_commission(q).await,
            Msg::ServiceStatus(q) => self.handle_service_status(q).await,
            Msg::TooLarge { q, device } => self.handle_too_large(q, device).await,
            Msg::Member(m, alive) => self.handle_member(&m, alive).await,
            Msg::Handover(q) => self.handle_handover(q).await,
            Msg::HandedOver { devices, in_step } => {
                let mut c = lock(&self.shared.core);
                for d in &devices {
                    c.registry.handed_over(d, in_step);
                }
            }
            Msg::Answer {
                shard,
                kind,
                from,
                reply,
            } => self.handle_answer((shard, &from), kind, reply).await,
        }
    }

    /// Serve what waits in the inboxes: up to [`BATCH`] samples and [`GATEWAY_TURN`]
    /// batches, then let the other inputs have their turn.
    async fn serve_waiting(&mut self) {
        let shared = &self.shared;
        for _ in 0..BATCH {
            let out = {
                let mut c = lock(&shared.core);
                let Some(taken) = lock(&shared.inbox).pop() else {
                    break;
                };
                let dev = taken.id.clone();
                let answers = shared.masks.answers(protocol::shard_of(&dev));
                c.serve_sample(answers, &shared.inbox, taken)
                    .map(|cmd| (dev, cmd))
            };
            if let Some((dev, cmd)) = out {
                publish(&self.session, &shared.core, &dev, &cmd).await;
            }
        }
        let mut served = 0;
        while served < GATEWAY_TURN {
            let Some(taken) = lock(&shared.gateways).pop() else {
                break;
            };
            let gw = taken.id;
            let answers = shared.masks.answers(protocol::shard_of(&gw));
            // A split period's parts in the order they came: each plant's samples in order.
            for batch in taken.item.into_vec() {
                served += 1;
                let out = lock(&shared.core).serve_batch(
                    answers,
                    (&shared.inbox, &shared.drops),
                    &gw,
                    batch,
                );
                if let Some(payload) = out {
                    publish_batch(&self.session, &shared.core, gw.clone(), payload).await;
                }
            }
        }
        if !lock(&shared.inbox).is_empty() || !lock(&shared.gateways).is_empty() {
            // More waits: come back after the other inputs had their turn.
            shared.wake.notify_one();
        }
    }
}

/// The next scrape request, or never without metrics.
async fn next_scrape(scrapes: &mut Option<mpsc::Receiver<ScrapeRequest>>) -> Option<ScrapeRequest> {
    match scrapes.as_mut() {
        Some(s) => s.recv().await,
        None => std::future::pending().await,
    }
}

/// Restore the devices' snapshots from the directory the file names, and attach them to
/// the recording: a replay starts from the state these devices were restored to.
fn restore_snapshots(registry: &mut Registry, sn: &SnapshotSpec, observers: &Observers) {
    let loaded = crate::snapshot::load_dir(registry, &sn.dir);
    for (file, reason) in &loaded.refused {
        tracing::warn!(file = %file.display(), "snapshot not restored: {reason}");
    }
    tracing::info!(dir = %sn.dir.display(), restored = loaded.restored, refused = loaded.refused.len(), "snapshots");
    let Some(r) = observers.recording.as_ref().filter(|_| loaded.restored > 0) else {
        return;
    };
    for snap in registry.snapshots() {
        if snap.last_seq.is_some() {
            if let Ok(bytes) = crate::snapshot::encode(&snap) {
                r.attach(
                    &format!("snapshot/{}", snap.id),
                    "application/x-mfc-snapshot",
                    bytes,
                );
            }
        }
    }
}

/// Join the fleet: listen to the members and to requests, look for the members already
/// there (what was theirs stays theirs until they hand it over), then declare this
/// member's token.
async fn join_fleet(
    session: &Session,
    intake: &Arc<Intake>,
    id: &str,
    spec: &FleetSpec,
) -> Result<(FleetRoutes, Member, Vec<ShardAction>), ServiceError> {
    let listening = FleetRoutes::declare(session, intake, (&spec.name, id)).await?;
    let wait = Duration::from_millis(spec.discover_ms);
    let others = super::routes::fleet_members(session, &spec.name, id, wait).await;
    // The token before any request: a member that hears from this one can also hear it
    // leave.
    let routes = FleetRoutes::join(session, listening, (&spec.name, id)).await?;
    tracing::info!(controller = %id, fleet = %spec.name, others = ?others, "joining the fleet");
    let timing = FleetTiming {
        release_timeout: Duration::from_millis(spec.release_timeout_ms),
        retry: FleetTiming::default().retry,
    };
    let mut fleet = Fleet::new(id, spec.standby, timing);
    let actions = fleet.start(others);
    let holds = super::hold::Replicator {
        session: session.clone(),
        fleet: spec.name.clone(),
        me: id.to_string(),
        keys: intake.shared.keys.clone(),
        timeout: Duration::from_millis(spec.handover_timeout_ms),
        tx: intake.tx.clone(),
        shared: intake.shared.clone(),
    }
    .spawn();
    let member = Member {
        fleet,
        spec: spec.clone(),
        holds,
    };
    Ok((routes, member, actions))
}

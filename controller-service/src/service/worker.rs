//! The worker: it owns the registry (through the [`Core`] it shares with zenoh's
//! callbacks), waits for whatever comes next, and hands each event to one handler. The
//! handlers of operators' queries are in [`super::requests`], those of the fleet and the
//! hot standby in [`super::handover`].

use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use protocol::{keys, pb, printable};
use tokio::sync::{mpsc, Notify};
use tokio::time::{interval, Interval, MissedTickBehavior};
use zenoh::liveliness::LivelinessToken;
use zenoh::Session;

use super::core::{publish, publish_batch, record_config, Core, Masks, Shared, Watch};
use super::intake::{Drops, Intake, Msg, UNKNOWN_NAMED};
use super::keyring::Keyring;
use super::log::{throttled, Warnings};
use super::routes::{FleetRoutes, Routes, ShardRoutes, StandbyRoutes, Twins};
use super::{declare_err, lock, ServiceError};
use super::{
    BATCH, FLEET_TICK, GATEWAYS_PENDING, GATEWAY_TURN, HEARTBEATS, LOG_INTERVAL, OTHERS, QUEUE,
};
use crate::config::{FleetSpec, SnapshotSpec};
use crate::fleet::{Fleet, FleetTiming, ShardAction};
use crate::inbox::Inbox;
use crate::observe::{Observers, ScrapeRequest, Scraped};
use crate::standby::HotStandby;
use crate::Registry;

/// A fleet member's view and its settings.
pub(super) struct Member {
    pub(super) fleet: Fleet,
    pub(super) spec: FleetSpec,
    /// The queue of accepted changes waiting for their partners ([`super::hold`]).
    pub(super) holds: mpsc::Sender<super::hold::HoldJob>,
}

/// One worker: its declarations (fields drop in order: its liveliness token goes first,
/// so plants and standbys see it leave at once), its shared core, and the state of its
/// rules.
pub(super) struct Worker {
    _token: LivelinessToken,
    _twins: super::routes::Twins,
    pub(super) standby_routes: Option<StandbyRoutes>,
    _routes: Routes,
    _fleet_routes: Option<FleetRoutes>,
    pub(super) shard_routes: ShardRoutes,
    pub(super) id: String,
    pub(super) session: Session,
    pub(super) shared: Arc<Shared>,
    pub(super) intake: Arc<Intake>,
    /// The worker's own queue, for the results of its request tasks.
    pub(super) tx: mpsc::Sender<Msg>,
    pub(super) member: Option<Member>,
    pub(super) standby: HotStandby,
    /// Operators' changes on their way ([`super::operators`]).
    pub(super) changes: super::operators::Changes,
    snapshots: Option<SnapshotSpec>,
    /// Throttles for what the worker logs (the core keeps its own).
    pub(super) warn: Warnings,
    /// The drop counts last reported, in the order [`Worker::report_drops`] logs them.
    reported: [u64; 8],
    started: Instant,
}

/// What the worker waits on besides its own fields.
pub(super) struct Inputs {
    rx: mpsc::Receiver<Msg>,
    /// The audit file's writer's word on this worker's records.
    written: mpsc::Receiver<super::trail::Written>,
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
        let (written_tx, written_rx) = mpsc::channel(super::trail::WAITING);
        let templates = registry.template_patterns();
        let keys = Keyring::of(&registry);
        let gate = super::operators::Gate::of(&registry, observers.audit.clone());
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
            changes: super::operators::Changes::new(written_tx),
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

    /// The metrics endpoint asks for this worker's status.
    fn handle_scrape(&self, req: ScrapeRequest) {
        let mut tally = crate::observe::Tally::default();
        let status = self.service_status_where(|id| req.detail.contains(id), Some(&mut tally));
        let _ = req.reply.send(Scraped {
            status,
            tally,
            inbox: lock(&self.shared.inbox).len(),
            gateways: lock(&self.shared.gateways).len(),
            queue: self.tx.max_capacity() - self.tx.capacity(),
        });
    }

    /// A sample the callback's precheck refused: answered REJECTED, if the device is
    /// served here.
    async fn handle_refused(&mut self, dev: &str, sample: &pb::Sample, reason: String) {
        let preferred = self.shared.masks.answers(protocol::shard_of(dev));
        let out = {
            let mut c = lock(&self.shared.core);
            let out = c
                .registry
                .refuse_sample(dev, sample, reason, protocol::unix_ns(), preferred);
            if let Some((cmd, _)) = &out {
                c.watch.refused(dev, cmd);
            }
            out
        };
        let Some((cmd, send)) = out else { return };
        throttled!(self.warn.rejected, warn, device = %dev, seq = sample.seq, "sample refused: {}", cmd.error);
        if send {
            publish(&self.session, &self.shared.core, dev, &cmd).await;
        }
    }

    /// Write the snapshots, if the file asks for them.
    fn save_snapshots(&self) {
        let Some(sn) = &self.snapshots else { return };
        let saved = tokio::task::block_in_place(|| {
            crate::snapshot::save_dir(&lock(&self.shared.core).registry, &sn.dir)
        });
        if let Err(e) = saved {
            tracing::warn!(dir = %sn.dir.display(), "writing snapshots: {e}");
        }
    }

    /// The callbacks' drops cannot log themselves (they run on zenoh's threads, possibly
    /// thousands of times a second): one line per interval, if any.
    fn report_drops(&mut self) {
        let shared = &self.shared;
        let (superseded, full) = {
            let ib = lock(&shared.inbox);
            (ib.superseded(), ib.full())
        };
        let (superseded_batches, gw_full) = {
            let gw = lock(&shared.gateways);
            (gw.superseded(), gw.full())
        };
        let full = full + gw_full;
        let [oversized, bad_key, queue_full, undecodable, unknown, forged] = shared.drops.counts();
        let now = [
            oversized,
            bad_key,
            queue_full + full,
            superseded,
            undecodable,
            unknown,
            forged,
            superseded_batches,
        ];
        let d: Vec<u64> = now.iter().zip(&self.reported).map(|(a, b)| a - b).collect();
        if d.iter().any(|&x| x > 0) {
            tracing::warn!(oversized = d[0], bad_key = d[1], queue_full = d[2], superseded = d[3], undecodable_samples = d[4],
                unknown_devices = d[5], forged = d[6], superseded_batches = d[7], "messages dropped since the last report (every drop is counted in the service status)");
        }
        self.reported = now;
        self.warn.flush(Instant::now());
    }

    /// The worker's status as a `ServiceStatus` query gets it: the registry's, with the
    /// drops counted before anything reached the worker and the standby and fleet state.
    pub(super) fn service_status(&self) -> pb::ServiceStatus {
        self.service_status_where(|_| true, None)
    }

    /// [`Self::service_status`] with only the devices `keep` says, and into `tally` the
    /// numbers of every device this worker answers for (at the same instant: one lock).
    fn service_status_where(
        &self,
        keep: impl Fn(&str) -> bool,
        tally: Option<&mut crate::observe::Tally>,
    ) -> pb::ServiceStatus {
        let shared = &self.shared;
        let core = lock(&shared.core);
        let registry = &core.registry;
        let mut s = registry.service_status_where(self.started.elapsed().as_secs_f64(), keep);
        let (superseded, full) = {
            let ib = lock(&shared.inbox);
            (ib.superseded(), ib.full())
        };
        let (superseded_batches, gw_full) = {
            let g = lock(&shared.gateways);
            (g.superseded(), g.full())
        };
        let [oversized, bad_key, queue_full, undecodable, unknown, forged] = shared.drops.counts();
        s.forged = forged;
        if let Some(t) = &core.gate.trail {
            use std::sync::atomic::Ordering::Relaxed;
            s.audit_written = t.stats.written.load(Relaxed);
            s.audit_errors = t.stats.errors.load(Relaxed);
        }
        s.authenticated = shared.keys.is_some();
        s.superseded_batches = superseded_batches;
        s.unknown_samples += unknown;
        for name in lock(&shared.drops.unknown_names).iter() {
            if s.unknown_devices.len() >= UNKNOWN_NAMED {
                break;
            }
            if !s.unknown_devices.contains(name) {
                s.unknown_devices.push(name.clone());
            }
        }
        s.oversized = oversized;
        s.undecodable += undecodable;
        s.bad_key = bad_key;
        s.queue_full = queue_full + full + gw_full;
        s.superseded = superseded;
        s.active = self.standby.active;
        s.term = self.standby.term;
        s.instance = registry.instance();
        s.twins = lock(&shared.twins).iter().copied().collect();
        let now = protocol::unix_ns();
        for d in &mut s.devices {
            registry.stamp(d, now);
        }
        // A fleet member (a worker among several too) keeps every device's state warm but
        // answers only for its shards: the others are not its to report.
        let answers = |id: &str| {
            self.member
                .as_ref()
                .is_none_or(|m| registry.home_of(id).is_some_and(|h| m.fleet.answers(h)))
        };
        if let Some(t) = tally {
            registry.for_each_counters(|id, d| {
                if answers(id) {
                    t.add(id, d);
                }
            });
        }
        if let Some(m) = &self.member {
            let f = &m.fleet;
            s.devices.retain(|d| answers(&d.device_id));
            s.owned_shards = (0..protocol::SHARDS).filter(|&x| f.answers(x)).collect();
            s.fleet_members = f.members().iter().cloned().collect();
        }
        s
    }

    /// Log a refusal of a device's request (throttled).
    pub(super) fn refused(&mut self, dev: &str, what: &str, reason: &str) {
        throttled!(self.warn.refused, warn, device = %printable(dev), "{what} refused: {reason}");
    }

    /// Count and log an undecodable payload.
    pub(super) fn undecodable(&mut self, what: &str, dev: &str, e: &protocol::DecodeError) {
        lock(&self.shared.core).registry.note_undecodable();
        throttled!(self.warn.undecodable, warn, device = %printable(dev), "undecodable {what}: {e}");
    }
}

impl Watch {
    /// What `registry`'s worker feeds `observers`; a recording starts with every device's
    /// configuration.
    fn of(registry: &Registry, observers: &Observers) -> Self {
        let watch = Self {
            controller: registry.controller_id().to_string(),
            recording: observers.recording.clone(),
            metrics: observers.metrics.clone(),
            histograms: HashMap::new(),
        };
        if let Some(r) = &watch.recording {
            for d in registry.device_ids() {
                record_config(r, registry, d, "recording starts");
            }
        }
        watch
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
    }
    .spawn();
    let member = Member {
        fleet,
        spec: spec.clone(),
        holds,
    };
    Ok((routes, member, actions))
}

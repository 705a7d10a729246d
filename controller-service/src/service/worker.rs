//! The worker's state: its declarations, the core it shares with zenoh's callbacks, its
//! fleet and standby roles and its changes on their way, with what every handler uses (the
//! service status, refusals logged). Its loop is in [`super::run`]; its handlers, which
//! build on this file and never the other way round, in [`super::requests`],
//! [`super::operators`] and [`super::handover`].

use std::sync::Arc;
use std::time::Instant;

use protocol::{pb, printable};
use tokio::sync::mpsc;
use zenoh::liveliness::LivelinessToken;
use zenoh::Session;

use super::change::Changes;
use super::core::{publish, Shared};
use super::drops::UNKNOWN_NAMED;
use super::intake::{Intake, Msg};
use super::locks::lock;
use super::log::{throttled, Warnings};
use super::routes::{FleetRoutes, Routes, ShardRoutes, StandbyRoutes, Twins};
use crate::config::{FleetSpec, SnapshotSpec};
use crate::fleet::Fleet;
use crate::observe::{ScrapeRequest, Scraped};
use crate::standby::HotStandby;

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
    pub(super) _token: LivelinessToken,
    pub(super) _twins: Twins,
    pub(super) standby_routes: Option<StandbyRoutes>,
    pub(super) _routes: Routes,
    pub(super) _fleet_routes: Option<FleetRoutes>,
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
    pub(super) changes: Changes,
    pub(super) snapshots: Option<SnapshotSpec>,
    /// Throttles for what the worker logs (the core keeps its own).
    pub(super) warn: Warnings,
    /// The drop counts last reported, in the order [`Worker::report_drops`] logs them.
    pub(super) reported: [u64; 8],
    pub(super) started: Instant,
}

impl Worker {
    /// The metrics endpoint asks for this worker's status.
    pub(super) fn handle_scrape(&self, req: ScrapeRequest) {
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
    pub(super) async fn handle_refused(&mut self, dev: &str, sample: &pb::Sample, reason: String) {
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
    pub(super) fn save_snapshots(&self) {
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
    pub(super) fn report_drops(&mut self) {
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
    pub(super) fn service_status_where(
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

//! The controller service on Zenoh: subscriptions, queryables, liveliness, and one worker
//! task that owns the [`Registry`] (no locks on the hot path).
//!
//! Zenoh's callbacks only copy the payload into a bounded channel (they run on zenoh's
//! receive threads and must never block); the worker decodes, steps the controllers and
//! publishes. If the channel is full the message is dropped and counted: in a control loop
//! the next sample supersedes it anyway.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Instant;

use protocol::{decode, encode, keys, pb};
use tokio::sync::mpsc;
use zenoh::pubsub::Publisher;
use zenoh::query::Query;
use zenoh::Session;

use crate::registry::{Outcome, Registry};

/// Messages from zenoh's callbacks to the worker.
enum Msg {
    /// A sample's key (it names the device) and undecoded payload.
    Sample(String, Vec<u8>),
    /// A heartbeat of the group, this member's own included (`on_heartbeat` skips those).
    Heartbeat(Vec<u8>),
    /// A live reference update's key and undecoded payload.
    Reference(String, Vec<u8>),
    /// A config query: a read without payload, a change with one.
    Config(Query),
    /// A device status query; a wildcard key gets one reply per device.
    Status(Query),
    /// A service status query, answered with the hot-standby state and the queue drops.
    ServiceStatus(Query),
}

/// Depth of the callback-to-worker channel (messages). When it is full new messages are
/// dropped; dropped samples are added to `decode_errors` in the service status.
const QUEUE: usize = 8192;

/// Why the service stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    /// A zenoh declaration failed.
    #[error("declaring {what}: {reason}")]
    Declare {
        /// What was being declared, e.g. `sample subscriber`, `liveliness token`.
        what: String,
        /// zenoh's reason.
        reason: String,
    },
}

fn declare_err(what: impl Into<String>) -> impl FnOnce(zenoh::Error) -> ServiceError {
    let what = what.into();
    move |e| ServiceError::Declare {
        what,
        reason: e.to_string(),
    }
}

/// Run the service on `session` until `shutdown` resolves; then undeclare everything
/// (the liveliness token disappears at once, so plants and standbys see a clean exit).
pub async fn serve(
    session: Session,
    mut registry: Registry,
    shutdown: impl std::future::Future<Output = ()>,
) -> Result<(), ServiceError> {
    let started = Instant::now();
    let id = registry.controller_id().to_string();
    let snapshots = registry.snapshot_spec().cloned();
    if let Some(sn) = &snapshots {
        let (ok, refused) = registry.load_snapshots(&sn.dir);
        tracing::info!(dir = %sn.dir.display(), restored = ok, refused, "snapshots");
    }
    let (tx, mut rx) = mpsc::channel::<Msg>(QUEUE);
    let dropped = Arc::new(AtomicU64::new(0));

    let sub = {
        let (tx, dropped) = (tx.clone(), dropped.clone());
        session
            .declare_subscriber(keys::all_devices("sample"))
            .callback(move |s| {
                let msg = Msg::Sample(
                    s.key_expr().as_str().to_string(),
                    s.payload().to_bytes().into_owned(),
                );
                if tx.try_send(msg).is_err() {
                    dropped.fetch_add(1, Ordering::Relaxed);
                }
            })
            .await
            .map_err(declare_err("sample subscriber"))?
    };
    let ref_sub = {
        let tx = tx.clone();
        session
            .declare_subscriber(keys::all_devices("reference"))
            .callback(move |s| {
                let _ = tx.try_send(Msg::Reference(
                    s.key_expr().as_str().to_string(),
                    s.payload().to_bytes().into_owned(),
                ));
            })
            .await
            .map_err(declare_err("reference subscriber"))?
    };
    let q_config = {
        let tx = tx.clone();
        session
            .declare_queryable(keys::all_devices("config"))
            .callback(move |q| {
                let _ = tx.try_send(Msg::Config(q));
            })
            .await
            .map_err(declare_err("config queryable"))?
    };
    let q_status = {
        let tx = tx.clone();
        session
            .declare_queryable(keys::all_devices("status"))
            .callback(move |q| {
                let _ = tx.try_send(Msg::Status(q));
            })
            .await
            .map_err(declare_err("status queryable"))?
    };
    let q_service = {
        let tx = tx.clone();
        session
            .declare_queryable(keys::service_status(&id))
            .callback(move |q| {
                let _ = tx.try_send(Msg::ServiceStatus(q));
            })
            .await
            .map_err(declare_err("service status queryable"))?
    };
    // Hot standby: heartbeats of the group.
    let standby = registry.standby().cloned();
    let hb_sub = match &standby {
        Some(sb) => {
            let tx = tx.clone();
            Some(
                session
                    .declare_subscriber(keys::heartbeat(&sb.group))
                    .callback(move |s| {
                        let _ = tx.try_send(Msg::Heartbeat(s.payload().to_bytes().into_owned()));
                    })
                    .await
                    .map_err(declare_err("heartbeat subscriber"))?,
            )
        }
        None => None,
    };
    let hb_pub = match &standby {
        Some(sb) => Some(
            transport::control_publisher(&session, keys::heartbeat(&sb.group))
                .await
                .map_err(|e| ServiceError::Declare {
                    what: "heartbeat publisher".into(),
                    reason: e.to_string(),
                })?,
        ),
        None => None,
    };
    let mut ha = HotStandby::new(standby.as_ref());
    drop(tx);
    let token = session
        .liveliness()
        .declare_token(keys::alive_controller(&id))
        .await
        .map_err(declare_err("liveliness token"))?;
    tracing::info!(controller = %id, devices = registry.device_ids().count(), "serving");

    let mut publishers: HashMap<String, Publisher<'static>> = HashMap::new();
    let mut tick = tokio::time::interval(ha.heartbeat);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let mut snap_tick = tokio::time::interval(std::time::Duration::from_millis(
        snapshots.as_ref().map_or(3_600_000, |s| s.interval_ms),
    ));
    snap_tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    tokio::pin!(shutdown);
    loop {
        let msg = tokio::select! {
            m = rx.recv() => match m { Some(m) => m, None => break },
            _ = tick.tick(), if hb_pub.is_some() => {
                if ha.on_tick() {
                    tracing::warn!(controller = %id, term = ha.term, "no heartbeat from the active member: taking over");
                }
                if let (true, Some(p)) = (ha.active, &hb_pub) {
                    let hb = pb::Heartbeat { version: protocol::PROTOCOL_VERSION, controller_id: id.clone(), term: ha.term };
                    let _ = p.put(encode(&hb)).await;
                }
                continue;
            }
            _ = snap_tick.tick(), if snapshots.is_some() => {
                if let Some(sn) = &snapshots {
                    let saved = tokio::task::block_in_place(|| registry.save_snapshots(&sn.dir));
                    if let Err(e) = saved {
                        tracing::warn!(dir = %sn.dir.display(), "writing snapshots: {e}");
                    }
                }
                continue;
            }
            () = &mut shutdown => break,
        };
        match msg {
            Msg::Heartbeat(bytes) => {
                if let Ok(hb) = decode::<pb::Heartbeat>(&bytes) {
                    if ha.on_heartbeat(&id, &hb) {
                        tracing::warn!(controller = %id, other = %hb.controller_id, "another member is active: standing by");
                    }
                }
            }
            Msg::Sample(key, bytes) => {
                let Some(dev) = keys::device_of(&key) else {
                    continue;
                };
                let sample = match decode::<pb::Sample>(&bytes) {
                    Ok(s) => s,
                    Err(e) => {
                        registry.note_decode_error();
                        tracing::warn!(device = dev, "undecodable sample: {e}");
                        continue;
                    }
                };
                // Every member follows every sample (a standby stays warm); only the active
                // one answers.
                let outcome = registry.handle_sample(dev, &sample);
                if !ha.active {
                    continue;
                }
                if let Outcome::Reply(cmd) = outcome {
                    let publisher = match publishers.get(dev) {
                        Some(p) => p,
                        None => {
                            match transport::control_publisher(&session, keys::command(dev)).await {
                                Ok(p) => publishers.entry(dev.to_string()).or_insert(p),
                                Err(e) => {
                                    tracing::error!(device = dev, "{e}");
                                    continue;
                                }
                            }
                        }
                    };
                    if let Err(e) = publisher.put(encode(&cmd)).await {
                        tracing::warn!(device = dev, "publishing a command: {e}");
                    }
                }
            }
            Msg::Reference(key, bytes) => {
                let Some(dev) = keys::device_of(&key) else {
                    continue;
                };
                match decode::<pb::ReferenceUpdate>(&bytes) {
                    Ok(u) => {
                        if let Err(reason) = registry.set_reference(dev, &u) {
                            tracing::warn!(device = dev, "reference refused: {reason}");
                        }
                    }
                    Err(e) => {
                        registry.note_decode_error();
                        tracing::warn!(device = dev, "undecodable reference: {e}");
                    }
                }
            }
            Msg::Config(q) => {
                let Some(dev) = keys::device_of(q.key_expr().as_str()).map(str::to_string) else {
                    let _ = q.reply_err("not a device config key").await;
                    continue;
                };
                let reply = match q.payload().map(|p| p.to_bytes().into_owned()) {
                    None => match registry.config_of(&dev) {
                        Some(c) => pb::ConfigReply {
                            version: protocol::PROTOCOL_VERSION,
                            accepted: true,
                            reason: String::new(),
                            config: Some(c),
                        },
                        None => pb::ConfigReply {
                            version: protocol::PROTOCOL_VERSION,
                            accepted: false,
                            reason: format!("unknown device {dev:?}"),
                            config: None,
                        },
                    },
                    Some(bytes) => match decode::<pb::ConfigRequest>(&bytes) {
                        Ok(req) => registry.configure(&dev, &req),
                        Err(e) => {
                            registry.note_decode_error();
                            pb::ConfigReply {
                                version: protocol::PROTOCOL_VERSION,
                                accepted: false,
                                reason: e.to_string(),
                                config: registry.config_of(&dev),
                            }
                        }
                    },
                };
                if !reply.accepted {
                    tracing::warn!(device = %dev, "configuration refused: {}", reply.reason);
                }
                let key = q.key_expr().clone();
                let _ = q.reply(key, encode(&reply)).await;
            }
            Msg::Status(q) => {
                let dev = keys::device_of(q.key_expr().as_str()).map(str::to_string);
                match dev.and_then(|d| registry.device_status(&d)) {
                    Some(s) => {
                        let key = q.key_expr().clone();
                        let _ = q.reply(key, encode(&s)).await;
                    }
                    None => {
                        // Wildcard queries get one reply per device; unknown ids get none.
                        if q.key_expr().as_str().contains('*') {
                            let ids: Vec<String> =
                                registry.device_ids().map(str::to_string).collect();
                            for d in ids {
                                if let Some(s) = registry.device_status(&d) {
                                    let _ = q.reply(keys::status(&d), encode(&s)).await;
                                }
                            }
                        }
                    }
                }
            }
            Msg::ServiceStatus(q) => {
                let mut s = registry.service_status(started.elapsed().as_secs_f64());
                s.decode_errors += dropped.load(Ordering::Relaxed);
                s.active = ha.active;
                s.term = ha.term;
                let key = q.key_expr().clone();
                let _ = q.reply(key, encode(&s)).await;
            }
        }
    }
    tracing::info!(controller = %id, "shutting down");
    if let Some(sn) = &snapshots {
        if let Err(e) = registry.save_snapshots(&sn.dir) {
            tracing::warn!(dir = %sn.dir.display(), "writing snapshots: {e}");
        }
    }
    drop(token);
    drop(hb_sub);
    drop(hb_pub);
    drop(sub);
    drop(ref_sub);
    drop(q_config);
    drop(q_status);
    drop(q_service);
    drop(publishers);
    let _ = session.close().await;
    Ok(())
}

/// The hot-standby state machine (no I/O).
#[derive(Debug)]
pub struct HotStandby {
    /// Whether this member publishes commands and heartbeats. A standby still steps every
    /// sample, so its state is warm when it takes over.
    pub active: bool,
    /// Its term, sent in heartbeats and the status: at a takeover, one above the highest
    /// term it holds or has heard. When two members are active the higher term stays, and
    /// on equal terms the greater controller id.
    pub term: u64,
    /// Heartbeat period, also the period of the takeover check. 10 ms without a group,
    /// where nothing uses it.
    pub heartbeat: std::time::Duration,
    /// Silence after which a standby takes over; never (`Duration::MAX`) without a group.
    takeover: std::time::Duration,
    /// When another member was last heard; set one second ahead at start for a `standby`
    /// member (its grace).
    last_heard: Instant,
    /// Highest term heard from another member, so that a takeover outranks it.
    peer_term: u64,
}

impl HotStandby {
    /// Without a group the service is simply active; with one it starts silent and takes
    /// over after the takeover time (an `active` member at once if nobody speaks, a
    /// `standby` member after a grace of one second, so that it does not race the active
    /// one at start-up).
    pub fn new(spec: Option<&crate::config::StandbySpec>) -> Self {
        let now = Instant::now();
        match spec {
            None => Self {
                active: true,
                term: 0,
                heartbeat: std::time::Duration::from_millis(10),
                takeover: std::time::Duration::MAX,
                last_heard: now,
                peer_term: 0,
            },
            Some(sb) => Self {
                active: false,
                term: 0,
                heartbeat: std::time::Duration::from_millis(sb.heartbeat_ms),
                takeover: std::time::Duration::from_millis(sb.takeover_ms),
                last_heard: match sb.role {
                    crate::config::Role::Active => now,
                    crate::config::Role::Standby => now + std::time::Duration::from_secs(1),
                },
                peer_term: 0,
            },
        }
    }

    /// A heartbeat period passed; returns true if this member just took over.
    pub fn on_tick(&mut self) -> bool {
        let now = Instant::now();
        if !self.active && now > self.last_heard && now - self.last_heard > self.takeover {
            self.active = true;
            self.term = self.peer_term.max(self.term) + 1;
            return true;
        }
        false
    }

    /// A heartbeat from the group; returns true if this member just stepped down.
    pub fn on_heartbeat(&mut self, me: &str, hb: &pb::Heartbeat) -> bool {
        if hb.controller_id == me {
            return false;
        }
        self.last_heard = self.last_heard.max(Instant::now());
        self.peer_term = self.peer_term.max(hb.term);
        let they_win =
            hb.term > self.term || (hb.term == self.term && hb.controller_id.as_str() > me);
        if self.active && they_win {
            self.active = false;
            return true;
        }
        false
    }
}

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
    Sample(String, Vec<u8>),
    Reference(String, Vec<u8>),
    Config(Query),
    Status(Query),
    ServiceStatus(Query),
}

/// Depth of the callback-to-worker channel.
const QUEUE: usize = 8192;

/// Why the service stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    /// A zenoh declaration failed.
    #[error("declaring {what}: {reason}")]
    Declare {
        /// What.
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
pub async fn run(
    session: Session,
    mut registry: Registry,
    shutdown: impl std::future::Future<Output = ()>,
) -> Result<(), ServiceError> {
    let started = Instant::now();
    let id = registry.controller_id().to_string();
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
    drop(tx);
    let token = session
        .liveliness()
        .declare_token(keys::alive_controller(&id))
        .await
        .map_err(declare_err("liveliness token"))?;
    tracing::info!(controller = %id, devices = registry.device_ids().count(), "serving");

    let mut publishers: HashMap<String, Publisher<'static>> = HashMap::new();
    tokio::pin!(shutdown);
    loop {
        let msg = tokio::select! {
            m = rx.recv() => match m { Some(m) => m, None => break },
            () = &mut shutdown => break,
        };
        match msg {
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
                if let Outcome::Reply(cmd) = registry.handle_sample(dev, &sample) {
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
                let key = q.key_expr().clone();
                let _ = q.reply(key, encode(&s)).await;
            }
        }
    }
    tracing::info!(controller = %id, "shutting down");
    drop(token);
    drop(sub);
    drop(ref_sub);
    drop(q_config);
    drop(q_status);
    drop(q_service);
    drop(publishers);
    let _ = session.close().await;
    Ok(())
}

//! Every Zenoh declaration of a worker, owned by a struct: dropping it undeclares them
//! (zenoh's subscribers, queryables, tokens and publishers undeclare themselves on drop),
//! so the worker's end is its fields' drop order, and an error half-way through starting
//! undeclares whatever was declared before it.

use std::collections::HashMap;
use std::sync::Arc;

use protocol::keys;
use zenoh::liveliness::LivelinessToken;
use zenoh::pubsub::{Publisher, Subscriber};
use zenoh::query::Queryable;
use zenoh::Session;

use super::intake::Intake;
use crate::fleet::Fleet;

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

pub(super) fn declare_err(what: impl Into<String>) -> impl FnOnce(zenoh::Error) -> ServiceError {
    let what = what.into();
    move |e| ServiceError::Declare {
        what,
        reason: e.to_string(),
    }
}

/// The declarations every worker makes: samples, reference puts, gateway batches, the
/// device queries and the service status. Without a fleet, also the keys of every shard
/// (every shard is this service's); a fleet member declares those per shard
/// ([`ShardRoutes`]).
pub(super) struct Routes {
    _samples: Subscriber<()>,
    _references: Subscriber<()>,
    _gateways: Subscriber<()>,
    _device_queries: Vec<Queryable<()>>,
    _service_status: Queryable<()>,
    _all_shards: Option<AllShards>,
}

/// Without a fleet: every shard's samples and batches, and its device queries, one
/// queryable per queried leaf.
type AllShards = (Subscriber<()>, Subscriber<()>, Vec<Queryable<()>>);

impl Routes {
    pub(super) async fn declare(
        session: &Session,
        intake: &Arc<Intake>,
        controller: &str,
        fleet: bool,
    ) -> Result<Self, ServiceError> {
        let all_shards = if fleet {
            None
        } else {
            Some((
                subscribe(
                    session,
                    intake,
                    format!("{}/shard/*/device/*/sample", keys::PREFIX),
                    Kind::Sample,
                )
                .await?,
                subscribe(
                    session,
                    intake,
                    format!("{}/shard/*/gateway/*/samples", keys::PREFIX),
                    Kind::Gateway,
                )
                .await?,
                leaf_queries(session, intake, |leaf| {
                    format!("{}/shard/*/device/*/{leaf}", keys::PREFIX)
                })
                .await?,
            ))
        };
        let i = intake.clone();
        let service_status = session
            .declare_queryable(keys::service_status(controller))
            .callback(move |q| i.on_service_query(q))
            .await
            .map_err(declare_err("service status queryable"))?;
        Ok(Self {
            _samples: subscribe(session, intake, keys::all_devices("sample"), Kind::Sample).await?,
            _references: subscribe(
                session,
                intake,
                keys::served(&keys::all_devices("reference")),
                Kind::Reference,
            )
            .await?,
            _gateways: subscribe(
                session,
                intake,
                keys::all_gateways("samples"),
                Kind::Gateway,
            )
            .await?,
            _device_queries: leaf_queries(session, intake, keys::all_devices).await?,
            _service_status: service_status,
            _all_shards: all_shards,
        })
    }
}

/// What a subscription carries, and so which of [`Intake`]'s callbacks gets it.
#[derive(Debug, Clone, Copy)]
enum Kind {
    Sample,
    Gateway,
    Reference,
    Member,
    Heartbeat,
}

async fn subscribe(
    session: &Session,
    intake: &Arc<Intake>,
    key: String,
    kind: Kind,
) -> Result<Subscriber<()>, ServiceError> {
    let i = intake.clone();
    let callback = move |s| match kind {
        Kind::Sample => i.on_sample(s),
        Kind::Gateway => i.on_gateway_batch(s),
        Kind::Reference => i.on_reference(s),
        Kind::Member => i.on_member(s),
        Kind::Heartbeat => i.on_heartbeat(s),
    };
    let what = format!("{kind:?} subscriber on {key}").to_lowercase();
    match kind {
        Kind::Member => {
            session
                .liveliness()
                .declare_subscriber(key)
                .callback(callback)
                .await
        }
        _ => session.declare_subscriber(key).callback(callback).await,
    }
    .map_err(declare_err(what))
}

async fn device_queries(
    session: &Session,
    intake: &Arc<Intake>,
    key: String,
) -> Result<Queryable<()>, ServiceError> {
    let i = intake.clone();
    session
        .declare_queryable(key.clone())
        .callback(move |q| i.on_device_query(q))
        .await
        .map_err(declare_err(format!("device queryable on {key}")))
}

/// One device queryable per queried leaf (`keys::QUERIED_LEAVES`), each on `key(leaf)`
/// and the operators' keys below it (`keys::served`):
/// never one over every leaf, so that the deployment's access control can let a service
/// serve those leaves and nothing else (no `…/device/*/*`).
async fn leaf_queries(
    session: &Session,
    intake: &Arc<Intake>,
    key: impl Fn(&str) -> String,
) -> Result<Vec<Queryable<()>>, ServiceError> {
    let mut queryables = Vec::with_capacity(keys::QUERIED_LEAVES.len());
    for leaf in keys::QUERIED_LEAVES {
        queryables.push(device_queries(session, intake, keys::served(&key(leaf))).await?);
    }
    Ok(queryables)
}

/// A fleet member's own declarations: the members' tokens, the handover requests made to
/// it (changes to hold among them), and its own token (declared last, undeclared first: a
/// member that hears from this one can also hear it leave).
pub(super) struct FleetRoutes {
    _token: LivelinessToken,
    _members: Subscriber<()>,
    _handover: Queryable<()>,
}

impl FleetRoutes {
    /// Declare everything but the token, which [`FleetRoutes::join`] adds once the others
    /// have been looked for.
    pub(super) async fn declare(
        session: &Session,
        intake: &Arc<Intake>,
        (fleet, me): (&str, &str),
    ) -> Result<(Subscriber<()>, Queryable<()>), ServiceError> {
        let members = subscribe(session, intake, keys::fleet_members(fleet), Kind::Member).await?;
        let i = intake.clone();
        let handover = session
            .declare_queryable(format!("{}/shard/*", keys::fleet_member(fleet, me)))
            .callback(move |q| i.on_handover(q))
            .await
            .map_err(declare_err("handover queryable"))?;
        Ok((members, handover))
    }

    /// Declare the member's token: from now on the others see this member.
    pub(super) async fn join(
        session: &Session,
        (members, handover): (Subscriber<()>, Queryable<()>),
        (fleet, me): (&str, &str),
    ) -> Result<Self, ServiceError> {
        let token = session
            .liveliness()
            .declare_token(keys::fleet_member(fleet, me))
            .await
            .map_err(declare_err("fleet member token"))?;
        Ok(Self {
            _token: token,
            _members: members,
            _handover: handover,
        })
    }
}

/// The ids of the members already in the fleet, other than `me`, found within `wait`.
pub(super) async fn fleet_members(
    session: &Session,
    fleet: &str,
    me: &str,
    wait: std::time::Duration,
) -> Vec<String> {
    let mut others = Vec::new();
    let Ok(replies) = session
        .liveliness()
        .get(keys::fleet_members(fleet))
        .timeout(wait)
        .await
    else {
        return others;
    };
    while let Ok(r) = replies.recv_async().await {
        if let Ok(sample) = r.result() {
            if let Some(m) = keys::member_of(sample.key_expr().as_str()) {
                if m != me && !others.iter().any(|o| o == m) {
                    others.push(m.to_string());
                }
            }
        }
    }
    others
}

/// A member of a hot-standby group: the group's heartbeats, and its own publisher of them.
pub(super) struct StandbyRoutes {
    _heartbeats: Subscriber<()>,
    pub(super) publisher: Publisher<'static>,
}

impl StandbyRoutes {
    pub(super) async fn declare(
        session: &Session,
        intake: &Arc<Intake>,
        group: &str,
    ) -> Result<Self, ServiceError> {
        // The group's standbys hear only heartbeats: an operator's change lives on the
        // active member alone (its reply's `held_by` names it alone).
        tracing::warn!(group = %group, "hot-standby group: changes are held by the active member only; a fleet with standbys holds them on two");
        let heartbeats =
            subscribe(session, intake, keys::heartbeat(group), Kind::Heartbeat).await?;
        let publisher = transport::control_publisher(session, keys::heartbeat(group))
            .await
            .map_err(|e| ServiceError::Declare {
                what: "heartbeat publisher".into(),
                reason: e.to_string(),
            })?;
        Ok(Self {
            _heartbeats: heartbeats,
            publisher,
        })
    }
}

/// The shard subscriptions and queryables of a fleet member, declared as it takes shards
/// and dropped as it gives them up, so that zenoh routes it only its own shards' traffic.
#[derive(Default)]
pub(super) struct ShardRoutes {
    subs: HashMap<u32, (Subscriber<()>, Subscriber<()>)>,
    queryables: HashMap<u32, Vec<Queryable<()>>>,
}

impl ShardRoutes {
    /// Make the declarations match `fleet`'s roles: the traffic of every shard it steps,
    /// the queries of every shard it answers. A declaration that fails is logged and
    /// retried at the next call.
    pub(super) async fn sync(&mut self, session: &Session, intake: &Arc<Intake>, fleet: &Fleet) {
        let (step, answer) = (fleet.step_mask(), fleet.answer_mask());
        self.subs.retain(|s, _| step & (1u64 << s) != 0);
        self.queryables.retain(|s, _| answer & (1u64 << s) != 0);
        for shard in 0..protocol::SHARDS {
            if step & (1u64 << shard) != 0 && !self.subs.contains_key(&shard) {
                let a = subscribe(
                    session,
                    intake,
                    keys::shard_devices(shard, "sample"),
                    Kind::Sample,
                )
                .await;
                let b =
                    subscribe(session, intake, keys::shard_gateways(shard), Kind::Gateway).await;
                match (a, b) {
                    (Ok(a), Ok(b)) => {
                        self.subs.insert(shard, (a, b));
                    }
                    (Err(e), _) | (_, Err(e)) => tracing::error!(shard, "{e}"),
                }
            }
            if answer & (1u64 << shard) != 0 && !self.queryables.contains_key(&shard) {
                let key = |leaf: &str| keys::shard_devices(shard, leaf);
                match leaf_queries(session, intake, key).await {
                    Ok(q) => {
                        self.queryables.insert(shard, q);
                    }
                    Err(e) => tracing::error!(shard, "{e}"),
                }
            }
        }
    }
}

/// This process's own token among those carrying its controller id
/// (`keys::alive_instance`), and the watch on the others': a process that sees another
/// instance of its id (a copied bundle, a service started twice) says so once in its log,
/// and its status and metrics list it until it goes (`ServiceStatus.twins`).
pub(super) struct Twins {
    _token: LivelinessToken,
    _watch: Subscriber<()>,
}

impl Twins {
    pub(super) async fn declare(
        session: &Session,
        shared: &Arc<super::core::Shared>,
        (controller, instance): (&str, u64),
    ) -> Result<Self, ServiceError> {
        let id = controller.to_string();
        let seen = shared.clone();
        let watch = session
            .liveliness()
            .declare_subscriber(keys::alive_instances(controller))
            .history(true)
            .callback(move |s| {
                let Some(other) = keys::instance_of(&id, s.key_expr().as_str()) else {
                    return;
                };
                if other == instance {
                    return;
                }
                let alive = s.kind() == zenoh::sample::SampleKind::Put;
                let mut twins = super::locks::lock(&seen.twins);
                if alive && twins.insert(other) {
                    tracing::warn!(controller = %id, this = format!("{instance:016x}"), other = format!("{other:016x}"),
                        "another process carries this controller id (a copied bundle, or this service started twice): only one should run; the plants' leases keep them from commanding at once, but operators reach either");
                } else if !alive && twins.remove(&other) {
                    tracing::info!(controller = %id, other = format!("{other:016x}"), "the other process carrying this controller id is gone");
                }
            })
            .await
            .map_err(declare_err("instance watch"))?;
        let token = session
            .liveliness()
            .declare_token(keys::alive_instance(controller, instance))
            .await
            .map_err(declare_err("instance token"))?;
        Ok(Self {
            _token: token,
            _watch: watch,
        })
    }
}

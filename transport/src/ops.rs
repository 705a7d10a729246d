//! What an operator asks of the controllers, over a Zenoh session: each call is one query
//! (or a liveliness read) and returns the decoded answer or a typed error that says what
//! went wrong and where. No printing here: `mfcctl`'s `render` and the browser console
//! (`mfc-console`) present the answers, each in its own way.

use std::time::Duration;

use mfc::params::param;
use protocol::convert::update_field;
use protocol::{decode, encode, keys, pb, PROTOCOL_VERSION};
use zenoh::Session;

/// Why an operation failed.
#[derive(Debug, thiserror::Error)]
pub enum OpError {
    /// Nobody answered the query in time (no service up, or none reachable).
    #[error("{what}: no answer within {timeout_ms} ms (is a controller up and reachable?)")]
    NoAnswer {
        /// What was asked, with its key.
        what: String,
        /// The query timeout.
        timeout_ms: u64,
    },
    /// A controller answered with an error (for instance: it does not serve that device).
    #[error("{what}: {reason}")]
    Refused {
        /// What was asked, with its key.
        what: String,
        /// The controller's reason.
        reason: String,
    },
    /// An answer that is not the expected message.
    #[error("{what}: {source}")]
    Decode {
        /// What was asked, with its key.
        what: String,
        /// The decoder's reason.
        source: protocol::DecodeError,
    },
    /// The query could not be sent.
    #[error("{what}: {reason}")]
    Zenoh {
        /// What was asked, with its key.
        what: String,
        /// zenoh's reason.
        reason: String,
    },
    /// A request the operator wrote that cannot be sent as it is.
    #[error("{0}")]
    Usage(String),
}

/// Who asks: a session, and the operators' key (`protocol::auth::Secret::operator`) that
/// replies must be sealed with. A bare [`Session`] asks without one and takes any reply
/// (a deployment that runs open); an [`Operator`] with a key takes only replies sealed
/// for the key expression they came on and the request they answer, so a process that may
/// reply on a device's keys (any holder of a service certificate) cannot put words in the
/// controller's mouth.
pub trait Asker {
    /// The session queries go through.
    fn session(&self) -> &Session;
    /// The key replies must be sealed with, if any.
    fn key(&self) -> Option<&protocol::auth::Key>;
    /// The operator's name, put in every request key on a device
    /// (`…/{leaf}/by/{name}`, [`keys::by`]); `None` asks as nobody.
    fn name(&self) -> Option<&str> {
        None
    }
}

impl Asker for Session {
    fn session(&self) -> &Session {
        self
    }
    fn key(&self) -> Option<&protocol::auth::Key> {
        None
    }
}

/// A session, the operators' key and the operator's name: replies are checked, requests
/// name who makes them ([`Asker`]).
#[derive(Clone)]
pub struct Operator {
    /// The session queries go through.
    pub session: Session,
    /// The operators' key (`None`: replies are taken unchecked).
    pub key: Option<protocol::auth::Key>,
    /// Who asks ([`default_name`]: under a deployment the name of the operator's
    /// certificate, which the router's access control holds it to). `None`:
    /// requests name nobody, which a service with an access section refuses.
    pub name: Option<String>,
}

/// Who an operator's tool asks as when not told: the name its zenoh configuration gives
/// it (`metadata.name`, written by `mfc-deploy`: the certificate's), else the local user.
pub fn default_name(zenoh: &crate::ZenohArgs) -> Option<String> {
    zenoh.config_name().or_else(local_user)
}

/// The local user's name as an operator's (from `USER` or `LOGNAME`), if it is a valid
/// key chunk. Without a deployment nothing proves it: services record it as unverified.
pub fn local_user() -> Option<String> {
    ["USER", "LOGNAME"]
        .iter()
        .filter_map(|v| std::env::var(v).ok())
        .find(|n| keys::check_id(n).is_ok())
}

impl Operator {
    /// The same session and key, asking as `name` (a console acting for the person
    /// logged in).
    pub fn as_named(&self, name: &str) -> Operator {
        Operator {
            name: Some(name.to_string()),
            ..self.clone()
        }
    }
}

impl Asker for Operator {
    fn session(&self) -> &Session {
        &self.session
    }
    fn key(&self) -> Option<&protocol::auth::Key> {
        self.key.as_ref()
    }
    fn name(&self) -> Option<&str> {
        self.name.as_deref()
    }
}

/// What an operator is told of a reply that does not prove it came from a controller.
pub const UNPROVEN: &str = "a reply without a valid proof of origin (ignored)";

/// How long a query on one device waits for other members' replies once a good one came:
/// the members that answer do so within milliseconds; one that is paused or cut off never
/// does, and the operator should not wait out the whole timeout for it.
pub const SETTLE: Duration = Duration::from_millis(300);

/// Every reply to a query on `key` (good ones decoded as `M`, errors as text), waiting at
/// most `timeout`, or `settle` after the first good one: a wildcard gets one reply per
/// service. With the asker's key, a reply not sealed for its key expression and this
/// request is an error ([`UNPROVEN`]).
///
/// The query is dropped rather than queued where a link is congested: a router forwarding
/// it to a member that stopped reading (paused, its link stuck) would otherwise block, and
/// hold the query back from the member that could answer.
async fn replies<M: protocol::Versioned>(
    asker: &impl Asker,
    key: &str,
    payload: Option<Vec<u8>>,
    (timeout, settle): (Duration, Option<Duration>),
) -> Result<Vec<Result<M, String>>, OpError> {
    // A request on a device's key names its operator; the reply comes back on that key.
    let named;
    let key = match asker.name() {
        Some(n) if keys::request_parts(key).is_some() => {
            named = keys::by(key, n);
            named.as_str()
        }
        _ => key,
    };
    let what = format!("query {key}");
    let mut get = asker
        .session()
        .get(key)
        .target(zenoh::query::QueryTarget::All)
        // Every reply, not one per key: zenoh's default consolidation keeps a single
        // reply per key expression, which can be a forger's in place of the controller's.
        .consolidation(zenoh::query::ConsolidationMode::None)
        .congestion_control(zenoh::qos::CongestionControl::Drop)
        .timeout(timeout);
    let request = payload.clone().unwrap_or_default();
    if let Some(p) = payload {
        get = get.payload(p);
    }
    let rx = get.await.map_err(|e| OpError::Zenoh {
        what: what.clone(),
        reason: e.to_string(),
    })?;
    let mut out = Vec::new();
    let mut until = None;
    loop {
        let next = match until {
            None => rx.recv_async().await,
            Some(t) => match tokio::time::timeout_at(t, rx.recv_async()).await {
                Ok(r) => r,
                Err(_) => break,
            },
        };
        let Ok(reply) = next else { break };
        let item = match reply.result() {
            Ok(s) => {
                let bytes = s.payload().to_bytes();
                let body = match asker.key() {
                    Some(k) => {
                        let ctx = protocol::auth::reply_context(s.key_expr().as_str(), &request);
                        k.open_in(protocol::auth::Kind::Reply, &ctx, &bytes)
                            .map_err(|_| UNPROVEN.to_string())
                    }
                    None => Ok(&bytes[..]),
                };
                match body {
                    Ok(body) => Ok(decode::<M>(body).map_err(|source| OpError::Decode {
                        what: what.clone(),
                        source,
                    })?),
                    Err(e) => Err(e),
                }
            }
            Err(e) => {
                let bytes = e.payload().to_bytes();
                // With a key, an error is shown only if a controller sealed it: a forger
                // must not be able to show an operator a refusal either.
                Err(match asker.key() {
                    Some(k) => {
                        let ctx = protocol::auth::reply_context(key, &request);
                        k.open_in(protocol::auth::Kind::ErrorReply, &ctx, &bytes)
                            .map(|t| String::from_utf8_lossy(t).into_owned())
                            .unwrap_or_else(|_| UNPROVEN.to_string())
                    }
                    None => {
                        String::from_utf8_lossy(protocol::auth::unchecked_body(&bytes)).into_owned()
                    }
                })
            }
        };
        if item.is_ok() && until.is_none() {
            until = settle.map(|d| tokio::time::Instant::now() + d);
        }
        out.push(item);
    }
    Ok(out)
}

/// The good reply of the controller that serves the device (others say they do not, with
/// an error); the first error if no controller answered well.
async fn one<M: protocol::Versioned>(
    session: &impl Asker,
    key: &str,
    payload: Option<Vec<u8>>,
    timeout: Duration,
) -> Result<M, OpError> {
    let mut all = replies::<M>(session, key, payload, (timeout, Some(SETTLE))).await?;
    match all.iter().position(Result::is_ok) {
        Some(i) => Ok(all.swap_remove(i).expect("a good reply")),
        None => Err(first_error(key, all, timeout)),
    }
}

/// The status of every controller that answers, by controller id.
pub async fn services(
    session: &impl Asker,
    timeout: Duration,
) -> Result<Vec<pb::ServiceStatus>, OpError> {
    let key = format!("{}/service/*/status", keys::PREFIX);
    let mut out: Vec<pb::ServiceStatus> = replies(session, &key, None, (timeout, None))
        .await?
        .into_iter()
        .filter_map(Result::ok)
        .collect();
    out.sort_by(|a, b| a.controller_id.cmp(&b.controller_id));
    Ok(out)
}

/// Ids of the plants and of the controllers whose liveliness tokens are up.
pub async fn alive(session: &Session, what: &str) -> Result<Vec<String>, OpError> {
    let key = format!("{}/alive/{what}/*", keys::PREFIX);
    let rx = session
        .liveliness()
        .get(&key)
        .await
        .map_err(|e| OpError::Zenoh {
            what: format!("liveliness {key}"),
            reason: e.to_string(),
        })?;
    let mut ids = Vec::new();
    while let Ok(reply) = rx.recv_async().await {
        if let Ok(s) = reply.result() {
            if let Some(id) = s.key_expr().as_str().rsplit('/').next() {
                ids.push(id.to_string());
            }
        }
    }
    ids.sort();
    ids.dedup();
    Ok(ids)
}

/// One device's status, from the controller that serves it: where several members
/// answer (one resumed after a pause still believing it holds the plant, say), the one
/// that heard the plant last ([`device_statuses`]).
pub async fn device_status(
    session: &impl Asker,
    id: &str,
    timeout: Duration,
) -> Result<pb::DeviceStatus, OpError> {
    let mut all = device_statuses(session, id, timeout).await?;
    Ok(all.remove(0))
}

/// Every member's status of a device that answers for it, the one that heard the plant
/// last first (`DeviceStatus.heard_ms_ago`, each member's own clock; never heard comes
/// last): what the plant said last, whichever member heard it. At least one, or the
/// error [`one`] gives.
pub async fn device_statuses(
    session: &impl Asker,
    id: &str,
    timeout: Duration,
) -> Result<Vec<pb::DeviceStatus>, OpError> {
    check(id)?;
    let key = keys::status(id);
    let all = replies::<pb::DeviceStatus>(session, &key, None, (timeout, Some(SETTLE))).await?;
    let mut good: Vec<pb::DeviceStatus> = all.iter().filter_map(|r| r.clone().ok()).collect();
    if good.is_empty() {
        return Err(first_error(&key, all, timeout));
    }
    good.sort_by_key(|s| (s.heard_ms_ago == 0, s.heard_ms_ago));
    Ok(good)
}

/// The error of a query whose replies held no good one: the first proven error (a
/// controller's), else an unproven one, else no answer.
fn first_error<M>(key: &str, all: Vec<Result<M, String>>, timeout: Duration) -> OpError {
    let mut first_err: Option<String> = None;
    for e in all.into_iter().filter_map(Result::err) {
        if first_err.is_none() || first_err.as_deref() == Some(UNPROVEN) {
            first_err = Some(e);
        }
    }
    match first_err {
        Some(reason) => OpError::Refused {
            what: format!("query {key}"),
            reason,
        },
        None => OpError::NoAnswer {
            what: format!("query {key}"),
            timeout_ms: timeout.as_millis() as u64,
        },
    }
}

/// One device's configuration in force (laws, output maps, envelope, reference).
pub async fn config(
    session: &impl Asker,
    id: &str,
    timeout: Duration,
) -> Result<pb::DeviceConfig, OpError> {
    check(id)?;
    let reply: pb::ConfigReply = one(session, &keys::config(id), None, timeout).await?;
    accepted(&keys::config(id), reply)
}

/// A device's latest audit entries (`Some(id)`), or those of every device the asker may
/// see, one log per device, sorted by device.
pub async fn audit(
    asker: &impl Asker,
    id: Option<&str>,
    timeout: Duration,
) -> Result<Vec<pb::AuditLog>, OpError> {
    if let Some(id) = id {
        check(id)?;
        return Ok(vec![one(asker, &keys::audit(id), None, timeout).await?]);
    }
    let mut logs: Vec<pb::AuditLog> = replies(asker, &keys::audit("*"), None, (timeout, None))
        .await?
        .into_iter()
        .filter_map(Result::ok)
        .collect();
    logs.sort_by(|a, b| a.device_id.cmp(&b.device_id));
    logs.dedup_by(|a, b| a.device_id == b.device_id);
    Ok(logs)
}

/// A partial change of one channel: only the fields of `update` that are set change.
pub async fn update(
    session: &impl Asker,
    id: &str,
    update: pb::ChannelUpdate,
    timeout: Duration,
) -> Result<Changed, OpError> {
    check(id)?;
    let req = pb::ConfigRequest {
        version: PROTOCOL_VERSION,
        updates: vec![update],
        ..Default::default()
    };
    let reply: pb::ConfigReply =
        one(session, &keys::config(id), Some(encode(&req)), timeout).await?;
    changed(&keys::config(id), reply)
}

/// Replace the device's reference (answered: a refusal comes back with its reason).
pub async fn set_reference(
    session: &impl Asker,
    id: &str,
    reference: pb::Reference,
    timeout: Duration,
) -> Result<Changed, OpError> {
    check(id)?;
    let u = pb::ReferenceUpdate {
        version: PROTOCOL_VERSION,
        reference: Some(reference),
    };
    let reply: pb::ConfigReply =
        one(session, &keys::reference(id), Some(encode(&u)), timeout).await?;
    changed(&keys::reference(id), reply)
}

/// Change the device's envelope (narrowing; widening only where the service allows it).
pub async fn change_envelope(
    session: &impl Asker,
    id: &str,
    envelope: pb::Envelope,
    reason: &str,
    timeout: Duration,
) -> Result<Changed, OpError> {
    check(id)?;
    let req = pb::EnvelopeRequest {
        version: PROTOCOL_VERSION,
        envelope: Some(envelope),
        reason: reason.into(),
    };
    let reply: pb::ConfigReply =
        one(session, &keys::envelope(id), Some(encode(&req)), timeout).await?;
    changed(&keys::envelope(id), reply)
}

/// A commissioning request (start, confirm, abort; see `CommissionRequest` in the
/// `.proto`): the reply is the configuration in force afterwards, the run's progress is in
/// the device's status ([`device_status`], `commission`).
pub async fn commission(
    session: &impl Asker,
    id: &str,
    request: pb::CommissionRequest,
    timeout: Duration,
) -> Result<Changed, OpError> {
    check(id)?;
    let req = pb::CommissionRequest {
        version: PROTOCOL_VERSION,
        ..request
    };
    let reply: pb::ConfigReply =
        one(session, &keys::commission(id), Some(encode(&req)), timeout).await?;
    changed(&keys::commission(id), reply)
}

/// A `FIELD=VALUE` list as a partial change of `channel`: only the named fields are set,
/// so the service changes those and nothing else. The names are the tunable parameters of
/// the core's table ([`mfc::params::PARAMS`]), the fields of a [`pb::ChannelUpdate`]
/// ([`protocol::convert::update_field`]). Shared by `mfcctl set` and the browser
/// console's gain form, so both accept exactly the same names.
pub fn parse_update(channel: u32, fields: &[String]) -> Result<pb::ChannelUpdate, OpError> {
    let mut u = pb::ChannelUpdate {
        channel,
        ..Default::default()
    };
    for f in fields {
        let (k, v) = f
            .split_once('=')
            .ok_or_else(|| OpError::Usage(format!("{f:?}: write FIELD=VALUE, e.g. kp=2.5")))?;
        let v: f64 = v
            .trim()
            .parse()
            .map_err(|_| OpError::Usage(format!("{f:?}: {v:?} is not a number")))?;
        let name = k.trim();
        let Some(slot) = param(name).and_then(|p| update_field(&mut u, p.name)) else {
            let known: Vec<&str> = mfc::params::names().collect();
            return Err(OpError::Usage(format!(
                "unknown field {name:?}: {}",
                known.join(" ")
            )));
        };
        *slot = Some(v);
    }
    Ok(u)
}

fn check(id: &str) -> Result<(), OpError> {
    keys::check_id(id)
        .map(|_| ())
        .map_err(|e| OpError::Usage(e.to_string()))
}

/// A change the service accepted: the configuration now in force, and who holds it.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Changed {
    /// The device's configuration with the change in it.
    pub config: pb::DeviceConfig,
    /// The fleet members holding the change (the one commanding the plant first): the
    /// change outlives any one of them. One name in a fleet without standbys or a single
    /// service: then it lives as long as that member does, or its audit file.
    pub held_by: Vec<String>,
    /// Whether the change and its audit entry were on the answering member's stable
    /// storage (its audit file) before it was put in force: a restart keeps it.
    pub durable: bool,
}

fn changed(key: &str, reply: pb::ConfigReply) -> Result<Changed, OpError> {
    let (held_by, durable) = (reply.held_by.clone(), reply.durable);
    accepted(key, reply).map(|config| Changed {
        config,
        held_by,
        durable,
    })
}

fn accepted(key: &str, reply: pb::ConfigReply) -> Result<pb::DeviceConfig, OpError> {
    if !reply.accepted {
        return Err(OpError::Refused {
            what: format!("query {key}"),
            reason: reply.reason,
        });
    }
    reply.config.ok_or_else(|| OpError::Refused {
        what: format!("query {key}"),
        reason: "accepted, but no configuration came back".into(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn field_assignments_become_a_partial_change() {
        let u = parse_update(1, &["kp=450".into(), "alpha = 5".into()]).unwrap();
        assert_eq!(
            (u.channel, u.kp, u.alpha, u.ki),
            (1, Some(450.0), Some(5.0), None)
        );
        for bad in ["kp", "kp=x", "gain=1"] {
            assert!(parse_update(0, &[bad.into()]).is_err(), "{bad}");
        }
        // Every name of the table is accepted, and sets the field of that name.
        for (i, p) in mfc::params::PARAMS.iter().enumerate() {
            let mut u = parse_update(0, &[format!("{}={i}", p.name)]).unwrap();
            assert_eq!(*update_field(&mut u, p.name).unwrap(), Some(i as f64));
        }
        let e = parse_update(0, &["gain=1".into()]).unwrap_err().to_string();
        assert!(
            e.contains("unknown field \"gain\"") && e.contains("hold_after"),
            "{e}"
        );
    }
}

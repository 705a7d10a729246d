//! The key-expression layout, in one place.
//!
//! | key | direction | what |
//! |---|---|---|
//! | `mfc/v1/device/{id}/sample` | plant → controller, pub/sub | [`Sample`](crate::pb::Sample) every period |
//! | `mfc/v1/device/{id}/command` | controller → plant, pub/sub | [`Command`](crate::pb::Command) answering a sample |
//! | `mfc/v1/device/{id}/config` | queryable on the controller | read (empty query) or change ([`ConfigRequest`](crate::pb::ConfigRequest) → [`ConfigReply`](crate::pb::ConfigReply)) |
//! | `mfc/v1/device/{id}/status` | queryable on the controller | [`DeviceStatus`](crate::pb::DeviceStatus) |
//! | `mfc/v1/device/{id}/reference` | operator → controller, pub/sub or query | [`ReferenceUpdate`](crate::pb::ReferenceUpdate), steer the reference live (a query is answered with a [`ConfigReply`](crate::pb::ConfigReply)) |
//! | `mfc/v1/device/{id}/envelope` | queryable on the controller | read (empty query) or change the safety envelope ([`EnvelopeRequest`](crate::pb::EnvelopeRequest) → [`ConfigReply`](crate::pb::ConfigReply)) |
//! | `mfc/v1/device/{id}/audit` | queryable on the controller | [`AuditLog`](crate::pb::AuditLog): the device's latest audited changes |
//! | `mfc/v1/device/{id}/{leaf}/by/{operator}` | operator → controller | any of the five requests above, naming the operator who makes it ([`by`]); a deployment's access control lets an operator's certificate use its own name only |
//! | `mfc/v1/service/{controller}/status` | queryable on the controller | [`ServiceStatus`](crate::pb::ServiceStatus) |
//! | `mfc/v1/group/{group}/heartbeat` | active controller → its group | [`Heartbeat`](crate::pb::Heartbeat), hot standby |
//! | `mfc/v1/alive/controller/{controller}` | liveliness token | a controller is up |
//! | `mfc/v1/alive/plant/{id}` | liveliness token | a plant agent is up |
//! | `mfc/v1/shard/{s}/device/{id}/sample` | plant → controller, pub/sub | the same [`Sample`](crate::pb::Sample) with the device's shard `s` ([`shard_of`](crate::shard_of)) in the key, so that zenoh routes it only to the fleet member owning that shard; the agent publishes here |
//! | `mfc/v1/shard/{s}/device/{id}/{config,status,envelope,reference}` | queryables on the shard's owner only | as the keys without `shard/{s}`, which every member declares and only the owner answers |
//! | `mfc/v1/shard/{s}/gateway/{gateway}/samples` | gateway → controller | a [`SampleBatch`](crate::pb::SampleBatch), `s` the gateway's shard |
//! | `mfc/v1/fleet/{fleet}/member/{controller}` | liveliness token | a member of a fleet of service instances is up |
//! | `mfc/v1/fleet/{fleet}/member/{controller}/shard/{s}` | queryable on each member | handover of a shard's state to another member, and a change to hold before the member that accepted it acknowledges it |
//! | `mfc/v1/gateway/{gateway}/samples` | gateway → controller, pub/sub | [`SampleBatch`](crate::pb::SampleBatch): the samples of all its plants, every period |
//! | `mfc/v1/gateway/{gateway}/commands` | controller → gateway, pub/sub | [`CommandBatch`](crate::pb::CommandBatch) answering a batch |
//!
//! The version is in the prefix so that two incompatible generations never exchange a
//! byte. Device and controller ids are single key chunks: letters, digits, `-`, `_`, `.`.

/// Prefix of every key of this protocol version.
pub const PREFIX: &str = "mfc/v1";

/// Why an id cannot be used in a key expression.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("invalid id {id:?}: use 1 to 64 letters, digits, '-', '_' or '.'")]
pub struct InvalidId {
    /// The id.
    pub id: String,
}

/// Check a device or controller id.
pub fn check_id(id: &str) -> Result<&str, InvalidId> {
    let ok = !id.is_empty()
        && id.len() <= 64
        && id
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_' || b == b'.');
    if ok {
        Ok(id)
    } else {
        Err(InvalidId { id: id.into() })
    }
}

/// `mfc/v1/device/{id}/sample`.
pub fn sample(id: &str) -> String {
    format!("{PREFIX}/device/{id}/sample")
}
/// `mfc/v1/device/{id}/command`.
pub fn command(id: &str) -> String {
    format!("{PREFIX}/device/{id}/command")
}
/// `mfc/v1/device/{id}/config`.
pub fn config(id: &str) -> String {
    format!("{PREFIX}/device/{id}/config")
}
/// `mfc/v1/device/{id}/status`.
pub fn status(id: &str) -> String {
    format!("{PREFIX}/device/{id}/status")
}
/// `mfc/v1/device/{id}/reference`.
pub fn reference(id: &str) -> String {
    format!("{PREFIX}/device/{id}/reference")
}
/// `mfc/v1/device/{id}/envelope`.
pub fn envelope(id: &str) -> String {
    format!("{PREFIX}/device/{id}/envelope")
}
/// `mfc/v1/service/{controller}/status`.
pub fn service_status(controller: &str) -> String {
    format!("{PREFIX}/service/{controller}/status")
}
/// `mfc/v1/group/{group}/heartbeat`.
pub fn heartbeat(group: &str) -> String {
    format!("{PREFIX}/group/{group}/heartbeat")
}
/// `mfc/v1/alive/controller/{controller}`.
pub fn alive_controller(controller: &str) -> String {
    format!("{PREFIX}/alive/controller/{controller}")
}
/// `mfc/v1/alive/instance/{controller}/{instance}` (the instance in 16 hex digits): one
/// token per process, so that two processes carrying one controller id see each other.
pub fn alive_instance(controller: &str, instance: u64) -> String {
    format!("{PREFIX}/alive/instance/{controller}/{instance:016x}")
}
/// Every process's token of `controller` ([`alive_instance`]).
pub fn alive_instances(controller: &str) -> String {
    format!("{PREFIX}/alive/instance/{controller}/*")
}
/// The instance an [`alive_instance`] key names, if it is one of `controller`'s.
pub fn instance_of(controller: &str, key: &str) -> Option<u64> {
    let rest = key.strip_prefix(&format!("{PREFIX}/alive/instance/{controller}/"))?;
    (rest.len() == 16).then(|| u64::from_str_radix(rest, 16).ok())?
}
/// `mfc/v1/alive/plant/{id}`.
pub fn alive_plant(id: &str) -> String {
    format!("{PREFIX}/alive/plant/{id}")
}

/// `mfc/v1/gateway/{gateway}/samples`.
pub fn gateway_samples(gateway: &str) -> String {
    format!("{PREFIX}/gateway/{gateway}/samples")
}
/// `mfc/v1/gateway/{gateway}/commands`.
pub fn gateway_commands(gateway: &str) -> String {
    format!("{PREFIX}/gateway/{gateway}/commands")
}
/// Every gateway's `leaf` key: `mfc/v1/gateway/*/{leaf}`.
pub fn all_gateways(leaf: &str) -> String {
    format!("{PREFIX}/gateway/*/{leaf}")
}
/// The gateway id in a key `mfc/v1/[shard/{s}/]gateway/{gateway}/{leaf}`, if the key has
/// that shape (see [`gateway_key`]).
pub fn gateway_of(key: &str) -> Option<&str> {
    gateway_key(key).map(|(id, _)| id)
}

/// `mfc/v1/shard/{s}/device/{id}/{leaf}`, `s` the id's shard: where a plant agent
/// publishes its samples, so that zenoh routes them to their owner only.
pub fn shard_device(id: &str, leaf: &str) -> String {
    format!("{PREFIX}/shard/{}/device/{id}/{leaf}", crate::shard_of(id))
}
/// `mfc/v1/shard/{s}/device/{id}/sample`.
pub fn shard_sample(id: &str) -> String {
    shard_device(id, "sample")
}
/// Every device's `leaf` key in shard `s`: `mfc/v1/shard/{s}/device/*/{leaf}`.
pub fn shard_devices(shard: u32, leaf: &str) -> String {
    format!("{PREFIX}/shard/{shard}/device/*/{leaf}")
}
/// `mfc/v1/shard/{s}/gateway/{gateway}/samples`, `s` the gateway's shard.
pub fn shard_gateway_samples(gateway: &str) -> String {
    format!(
        "{PREFIX}/shard/{}/gateway/{gateway}/samples",
        crate::shard_of(gateway)
    )
}
/// Every gateway's batches in shard `s`: `mfc/v1/shard/{s}/gateway/*/samples`.
pub fn shard_gateways(shard: u32) -> String {
    format!("{PREFIX}/shard/{shard}/gateway/*/samples")
}
/// `mfc/v1/fleet/{fleet}/member/{controller}`: a member's liveliness token.
pub fn fleet_member(fleet: &str, controller: &str) -> String {
    format!("{PREFIX}/fleet/{fleet}/member/{controller}")
}
/// `mfc/v1/fleet/{fleet}/member/*`.
pub fn fleet_members(fleet: &str) -> String {
    format!("{PREFIX}/fleet/{fleet}/member/*")
}
/// `mfc/v1/fleet/{fleet}/member/{controller}/shard/{s}`: a member's handover queryable.
pub fn fleet_handover(fleet: &str, controller: &str, shard: u32) -> String {
    format!("{PREFIX}/fleet/{fleet}/member/{controller}/shard/{shard}")
}
/// The member id in a key `mfc/v1/fleet/{fleet}/member/{controller}[/...]`.
pub fn member_of(key: &str) -> Option<&str> {
    let rest = key.strip_prefix(PREFIX)?.strip_prefix("/fleet/")?;
    let (_fleet, rest) = rest.split_once('/')?;
    let rest = rest.strip_prefix("member/")?;
    let id = rest.split('/').next()?;
    check_id(id).ok()
}
/// The shard in a key whose last chunk is a shard number (`.../shard/{s}`),
/// if below [`SHARDS`](crate::SHARDS).
pub fn last_shard(key: &str) -> Option<u32> {
    let n: u32 = key.rsplit('/').next()?.parse().ok()?;
    (n < crate::SHARDS).then_some(n)
}

/// Strip an optional `shard/{s}/` after the prefix: `Some((shard, rest))`, `rest` starting
/// at `/device/` or `/gateway/`. A shard that is not a number below [`SHARDS`](crate::SHARDS)
/// gives `None`.
fn unshard(key: &str) -> Option<(Option<u32>, &str)> {
    let rest = key.strip_prefix(PREFIX)?;
    match rest.strip_prefix("/shard/") {
        Some(r) => {
            let slash = r.find('/')?;
            let n: u32 = r[..slash].parse().ok()?;
            (n < crate::SHARDS).then_some((Some(n), &r[slash..]))
        }
        None => Some((None, rest)),
    }
}

/// The device id and shard segment of `mfc/v1/device/{id}/{leaf}` or
/// `mfc/v1/shard/{s}/device/{id}/{leaf}`. A shard segment that is not the id's own shard
/// makes the key invalid (`None`): a plant cannot steer its traffic to another owner.
pub fn device_key(key: &str) -> Option<(&str, Option<u32>)> {
    let (shard, rest) = unshard(key)?;
    let rest = rest.strip_prefix("/device/")?;
    let (id, _leaf) = rest.split_once('/')?;
    let id = check_id(id).ok()?;
    match shard {
        Some(s) if s != crate::shard_of(id) => None,
        _ => Some((id, shard)),
    }
}

/// The gateway id of `mfc/v1/[shard/{s}/]gateway/{gateway}/{leaf}`, with the same rule.
pub fn gateway_key(key: &str) -> Option<(&str, Option<u32>)> {
    let (shard, rest) = unshard(key)?;
    let rest = rest.strip_prefix("/gateway/")?;
    let (id, _leaf) = rest.split_once('/')?;
    let id = check_id(id).ok()?;
    match shard {
        Some(s) if s != crate::shard_of(id) => None,
        _ => Some((id, shard)),
    }
}

/// The leaves of a device's key that a service answers queries on. A service declares one
/// queryable per leaf, not one on `device/*/*`: a deployment's access control (mfc-deploy)
/// lets a service declare exactly these, so a wider declaration would be refused by the
/// router and the service would answer nothing.
pub const QUERIED_LEAVES: [&str; 6] = [
    "config",
    "status",
    "envelope",
    "reference",
    "audit",
    "commission",
];

/// `mfc/v1/device/{id}/commission`.
pub fn commission(id: &str) -> String {
    format!("{PREFIX}/device/{id}/commission")
}

/// `mfc/v1/device/{id}/audit`.
pub fn audit(id: &str) -> String {
    format!("{PREFIX}/device/{id}/audit")
}

/// A request key naming its operator: `{key}/by/{operator}`. Services declare each
/// queried leaf as `…/{leaf}/**` ([`served`]) so that both shapes reach them.
pub fn by(key: &str, operator: &str) -> String {
    format!("{key}/by/{operator}")
}

/// The key expression a service declares for a request key `key` (e.g.
/// `mfc/v1/device/*/config`): the key itself and every `…/by/{operator}` below it.
pub fn served(key: &str) -> String {
    format!("{key}/**")
}

/// The leaf of a request on a device's key and the operator it names:
/// `mfc/v1/[shard/{s}/]device/{id}/{leaf}[/by/{operator}]`, where the shard and id may
/// be wildcards (a status query over many devices). `None` for any other shape, an
/// operator that is not a valid id included.
pub fn request_parts(key: &str) -> Option<(&str, Option<&str>)> {
    let mut rest = key.strip_prefix(PREFIX)?;
    if let Some(r) = rest.strip_prefix("/shard/") {
        rest = &r[r.find('/')?..];
    }
    let rest = rest.strip_prefix("/device/")?;
    let (_id, tail) = rest.split_once('/')?;
    match tail.split_once('/') {
        None => Some((tail, None)),
        Some((leaf, by)) => {
            let op = by.strip_prefix("by/")?;
            Some((leaf, Some(check_id(op).ok()?)))
        }
    }
}

/// Every device's `leaf` key (`sample`, `config`, ...): `mfc/v1/device/*/{leaf}`.
pub fn all_devices(leaf: &str) -> String {
    format!("{PREFIX}/device/*/{leaf}")
}

/// The device id in a key `mfc/v1/device/{id}/{leaf}` or
/// `mfc/v1/shard/{s}/device/{id}/{leaf}` (see [`device_key`]), if the key has that shape.
pub fn device_of(key: &str) -> Option<&str> {
    device_key(key).map(|(id, _)| id)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ids_and_keys() {
        assert_eq!(sample("aero-1"), "mfc/v1/device/aero-1/sample");
        assert_eq!(device_of("mfc/v1/device/aero-1/sample"), Some("aero-1"));
        assert_eq!(device_of("mfc/v1/device/a*b/sample"), None);
        assert_eq!(device_of("mfc/v2/device/x/sample"), None);
        for bad in ["", "a/b", "a*", "$x", "x y", &"x".repeat(65)] {
            assert!(check_id(bad).is_err(), "{bad:?}");
        }
        assert!(check_id("AERO_2.left").is_ok());
        assert_eq!(gateway_samples("cell-3"), "mfc/v1/gateway/cell-3/samples");
        assert_eq!(gateway_of(&gateway_commands("cell-3")), Some("cell-3"));
        assert_eq!(gateway_of("mfc/v1/device/x/sample"), None);
        // Shard segments: the id's own shard only.
        let k = shard_sample("aero-1");
        let s = crate::shard_of("aero-1");
        assert_eq!(k, format!("mfc/v1/shard/{s}/device/aero-1/sample"));
        assert_eq!(device_key(&k), Some(("aero-1", Some(s))));
        let wrong = format!(
            "mfc/v1/shard/{}/device/aero-1/sample",
            (s + 1) % crate::SHARDS
        );
        assert_eq!(device_of(&wrong), None);
        assert_eq!(device_of("mfc/v1/shard/64/device/aero-1/sample"), None);
        assert_eq!(device_of("mfc/v1/shard/x/device/aero-1/sample"), None);
        assert_eq!(
            device_key("mfc/v1/device/aero-1/sample"),
            Some(("aero-1", None))
        );
        let g = shard_gateway_samples("cell-3");
        assert_eq!(
            gateway_key(&g),
            Some(("cell-3", Some(crate::shard_of("cell-3"))))
        );
        // Requests name their operator after the leaf.
        let k = by(&config("aero-1"), "alice");
        assert_eq!(k, "mfc/v1/device/aero-1/config/by/alice");
        assert_eq!(device_of(&k), Some("aero-1"));
        assert_eq!(request_parts(&k), Some(("config", Some("alice"))));
        assert_eq!(request_parts(&config("aero-1")), Some(("config", None)));
        assert_eq!(
            request_parts("mfc/v1/shard/*/device/*/status/by/bob"),
            Some(("status", Some("bob")))
        );
        for bad in [
            "mfc/v1/device/aero-1/config/by/a*",
            "mfc/v1/device/aero-1/config/by",
            "mfc/v1/device/aero-1/config/as/alice",
            "mfc/v1/device/aero-1/config/by/alice/x",
            "mfc/v1/device/aero-1/config/**",
        ] {
            assert_eq!(request_parts(bad), None, "{bad}");
        }
        assert_eq!(member_of(&fleet_member("main", "c-2")), Some("c-2"));
        assert_eq!(member_of(&fleet_handover("main", "c-2", 7)), Some("c-2"));
        assert_eq!(last_shard(&fleet_handover("main", "c-2", 7)), Some(7));
    }
}

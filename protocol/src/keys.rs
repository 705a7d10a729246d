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
//! | `mfc/v1/service/{controller}/status` | queryable on the controller | [`ServiceStatus`](crate::pb::ServiceStatus) |
//! | `mfc/v1/group/{group}/heartbeat` | active controller → its group | [`Heartbeat`](crate::pb::Heartbeat), hot standby |
//! | `mfc/v1/alive/controller/{controller}` | liveliness token | a controller is up |
//! | `mfc/v1/alive/plant/{id}` | liveliness token | a plant agent is up |
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
/// `mfc/v1/alive/plant/{id}`.
pub fn alive_plant(id: &str) -> String {
    format!("{PREFIX}/alive/plant/{id}")
}

/// Every device's `leaf` key (`sample`, `config`, ...): `mfc/v1/device/*/{leaf}`.
pub fn all_devices(leaf: &str) -> String {
    format!("{PREFIX}/device/*/{leaf}")
}

/// The device id in a key `mfc/v1/device/{id}/{leaf}`, if the key has that shape.
pub fn device_of(key: &str) -> Option<&str> {
    let rest = key.strip_prefix(PREFIX)?.strip_prefix("/device/")?;
    let (id, _leaf) = rest.split_once('/')?;
    check_id(id).ok()
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
    }
}

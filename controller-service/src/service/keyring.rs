//! The service's side of the proof of origin (`protocol::auth`): the fleet's secret, and
//! the device and gateway keys derived from it, kept once derived.
//!
//! Deriving a key costs two HMAC computations; keeping it makes a sample cost one MAC to
//! check. The table is shared by zenoh's callbacks (which open samples before anything
//! else) and the worker (which seals commands), and bounded: it is cleared when full, so
//! a flood of templated ids costs derivations, never memory.

use std::collections::HashMap;
use std::sync::Mutex;

use protocol::auth::{Key, Kind, Secret};

use super::locks::lock;

/// Keys kept at most; beyond, the table starts again.
const KEPT: usize = 8192;

/// A fleet member's keys.
pub(super) struct Keyring {
    secret: Secret,
    devices: Mutex<HashMap<String, Key>>,
    gateways: Mutex<HashMap<String, Key>>,
    operator: Key,
    member: Key,
}

impl Keyring {
    /// The keys of `registry`'s member, if it has the fleet's secret; the log says which
    /// mode runs either way.
    pub(super) fn of(registry: &crate::Registry) -> Option<std::sync::Arc<Self>> {
        let id = registry.controller_id();
        match registry.secret() {
            Some(s) => {
                tracing::info!(
                    controller = %id,
                    "auth: keys (samples checked, commands and replies sealed)"
                );
                Some(std::sync::Arc::new(Self::new(s.clone())))
            }
            None => {
                tracing::warn!(
                    controller = %id,
                    "auth: open (no secret_file): samples are not checked and commands carry \
                     no proof of origin"
                );
                None
            }
        }
    }

    pub(super) fn new(secret: Secret) -> Self {
        Self {
            operator: secret.operator(),
            member: secret.member(),
            secret,
            devices: Mutex::new(HashMap::new()),
            gateways: Mutex::new(HashMap::new()),
        }
    }

    fn key(table: &Mutex<HashMap<String, Key>>, id: &str, derive: impl FnOnce() -> Key) -> Key {
        let mut t = lock(table);
        if let Some(k) = t.get(id) {
            return k.clone();
        }
        if t.len() >= KEPT {
            t.clear();
        }
        let k = derive();
        t.insert(id.to_string(), k.clone());
        k
    }

    fn device(&self, id: &str) -> Key {
        Self::key(&self.devices, id, || self.secret.device(id))
    }

    fn gateway(&self, id: &str) -> Key {
        Self::key(&self.gateways, id, || self.secret.gateway(id))
    }

    /// The body of device `id`'s sealed sample, or `None` (forged, altered, unsealed).
    pub(super) fn open_sample<'a>(&self, id: &str, bytes: &'a [u8]) -> Option<&'a [u8]> {
        self.device(id).open(Kind::Sample, bytes).ok()
    }

    /// The body of gateway `gw`'s sealed batch, or `None`.
    pub(super) fn open_batch<'a>(&self, gw: &str, bytes: &'a [u8]) -> Option<&'a [u8]> {
        self.gateway(gw).open(Kind::SampleBatch, bytes).ok()
    }

    /// A command for device `id`, sealed.
    pub(super) fn seal_command(&self, id: &str, bytes: Vec<u8>) -> Vec<u8> {
        self.device(id).seal(Kind::Command, bytes)
    }

    /// A command batch for gateway `gw`, sealed.
    pub(super) fn seal_batch(&self, gw: &str, bytes: Vec<u8>) -> Vec<u8> {
        self.gateway(gw).seal(Kind::CommandBatch, bytes)
    }

    /// A reply to an operator's query, sealed with the operators' key, bound to the
    /// reply's key expression and the query's payload (`protocol::auth::reply_context`).
    pub(super) fn seal_reply(&self, key_expr: &str, request: &[u8], bytes: Vec<u8>) -> Vec<u8> {
        let ctx = protocol::auth::reply_context(key_expr, request);
        self.operator.seal_in(Kind::Reply, &ctx, bytes)
    }

    /// An error reply to an operator's query, sealed like a good one but as an error.
    pub(super) fn seal_error(&self, key_expr: &str, request: &[u8], text: &str) -> Vec<u8> {
        let ctx = protocol::auth::reply_context(key_expr, request);
        self.operator
            .seal_in(Kind::ErrorReply, &ctx, text.as_bytes().to_vec())
    }
}

impl Keyring {
    /// A handover message between members (a shard's state, a change to hold, the
    /// answer), sealed with the members' key, bound to the key expression it travels on
    /// and, for an answer, to the request's payload.
    pub(super) fn seal_handover(&self, context: &[&[u8]], bytes: Vec<u8>) -> Vec<u8> {
        self.member.seal_in(Kind::Handover, context, bytes)
    }

    /// The body of a handover message sealed by a member, or `None`: a process without
    /// the fleet's secret (an operator, a device, a rogue holding only a certificate)
    /// cannot make a member restore a state or count a change as held.
    pub(super) fn open_handover<'a>(&self, context: &[&[u8]], bytes: &'a [u8]) -> Option<&'a [u8]> {
        self.member.open_in(Kind::Handover, context, bytes).ok()
    }
}

/// Seal with `keys` if the service has them (else the bytes go out as they are: open).
pub(super) fn sealed(
    keys: Option<&Keyring>,
    bytes: Vec<u8>,
    seal: impl FnOnce(&Keyring, Vec<u8>) -> Vec<u8>,
) -> Vec<u8> {
    match keys {
        Some(k) => seal(k, bytes),
        None => bytes,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn what_the_ring_seals_the_plants_keys_open_and_the_table_stays_bounded() {
        let secret = Secret::random().unwrap();
        let ring = Keyring::new(secret.clone());
        let cmd = ring.seal_command("aero-1", b"\x08\x01".to_vec());
        assert!(secret.device("aero-1").open(Kind::Command, &cmd).is_ok());
        assert!(secret.device("aero-2").open(Kind::Command, &cmd).is_err());
        let sample = secret
            .device("aero-1")
            .seal(Kind::Sample, b"\x08\x01".to_vec());
        assert_eq!(ring.open_sample("aero-1", &sample), Some(&b"\x08\x01"[..]));
        assert_eq!(ring.open_sample("aero-2", &sample), None);
        let batch = ring.seal_batch("gw", vec![]);
        assert!(secret
            .gateway("gw")
            .open(Kind::CommandBatch, &batch)
            .is_ok());
        for i in 0..KEPT + 10 {
            let _ = ring.open_sample(&format!("d{i}"), &sample);
        }
        assert!(lock(&ring.devices).len() <= KEPT);
        let reply = ring.seal_reply("mfc/v1/x", b"q", vec![1, 2]);
        let ctx = protocol::auth::reply_context("mfc/v1/x", b"q");
        assert!(secret.operator().open_in(Kind::Reply, &ctx, &reply).is_ok());
    }
}

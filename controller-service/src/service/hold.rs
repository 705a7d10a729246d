//! A change is acknowledged only once the members that would take the device over hold
//! it (`Fleet::partners`): the member that accepted it sends the device's new state to
//! each of them as a `hold:{id}` handover request and replies to the operator after their
//! answers. Without that, a takeover (the owner killed, paused or cut off) would carry on
//! with the state from before the change, and the operator, told "accepted", would never
//! learn that it was gone.
//!
//! One task per member carries the holds out, one after another, in the order the
//! changes were accepted: two quick changes to one device reach a partner in that order,
//! so a partner never ends holding the older one. The worker never waits: a partner that
//! does not answer delays the acknowledgments, not the samples, the handovers or the
//! heartbeats.
//!
//! Every handover payload is sealed with the members' key when the service has keys
//! ([`Keyring::seal_handover`]), bound to the key it travels on: a process holding a
//! service certificate but not the fleet's secret can neither make a member restore a
//! state nor pass for a partner that holds a change.

use std::sync::Arc;
use std::time::Duration;

use protocol::{encode, keys, pb};
use tokio::sync::mpsc;
use zenoh::query::Query;
use zenoh::Session;

use super::intake::Msg;
use super::keyring::Keyring;
use crate::lease::Holder;

/// Changes waiting for their holds at most; beyond, a change is answered at once as not
/// acknowledged (the operator sends it again).
pub(super) const PENDING: usize = 256;

/// One accepted change on its way to being held, or the states of the devices this
/// member commands on their way to a member that came (back) into its view.
pub(super) struct HoldJob {
    /// The operator's query, its payload (the reply is bound to it) and the reply as
    /// accepted here (`accepted`, `reason` and `held_by` are set from the holds); none
    /// for states sent to a member that came into view.
    pub(super) answer: Option<(Query, Vec<u8>, pb::ConfigReply)>,
    /// The devices' shard, and their state (`encode_shard`).
    pub(super) shard: u32,
    pub(super) state: Vec<u8>,
    /// The members that must hold it.
    pub(super) partners: Vec<String>,
    /// For states sent without a change: the devices, whose holder learns whether its
    /// partners are in step with it ([`Msg::HandedOver`]).
    pub(super) devices: Vec<String>,
}

/// Who this member is, and how it reaches its partners.
#[derive(Clone)]
pub(super) struct Replicator {
    pub(super) session: Session,
    pub(super) fleet: String,
    pub(super) me: String,
    pub(super) keys: Option<Arc<Keyring>>,
    pub(super) timeout: Duration,
    /// The worker's queue, for [`Msg::HandedOver`].
    pub(super) tx: mpsc::Sender<Msg>,
}

impl Replicator {
    /// Start the task that carries the holds out; its queue closes with the worker.
    pub(super) fn spawn(self) -> mpsc::Sender<HoldJob> {
        let (tx, mut rx) = mpsc::channel::<HoldJob>(PENDING);
        tokio::spawn(async move {
            while let Some(job) = rx.recv().await {
                self.carry_out(job).await;
            }
        });
        tx
    }

    async fn carry_out(&self, job: HoldJob) {
        let mut held = vec![self.me.clone()];
        let mut missing = Vec::new();
        let mut in_step = true;
        for p in &job.partners {
            match self.hold(p, job.shard, &job.state).await {
                Some(step) => {
                    held.push(p.clone());
                    in_step &= step;
                }
                None => missing.push(p.as_str()),
            }
        }
        let Some((query, request, mut reply)) = job.answer else {
            if !missing.is_empty() {
                tracing::debug!(shard = job.shard, members = ?missing, "devices' states did not reach their partners");
            }
            let handed = Msg::HandedOver {
                devices: job.devices,
                in_step: in_step && missing.is_empty(),
            };
            let _ = self.tx.send(handed).await;
            return;
        };
        let why = (!missing.is_empty()).then(|| {
            format!(
                "{} did not confirm holding it within {} ms",
                missing.join(" and "),
                self.timeout.as_millis()
            )
        });
        acknowledge(&mut reply, &self.me, held, why.as_deref());
        let key = query.key_expr().as_str().to_string();
        let bytes = match &self.keys {
            Some(k) => k.seal_reply(&key, &request, encode(&reply)),
            None => encode(&reply),
        };
        let _ = query.reply(query.key_expr().clone(), bytes).await;
    }

    /// Ask `partner` to hold `state`: once it said so (sealed, when with keys), whether
    /// it is in step with this member's devices; `None` if it did not.
    async fn hold(&self, partner: &str, shard: u32, state: &[u8]) -> Option<bool> {
        let key = keys::fleet_handover(&self.fleet, partner, shard);
        let head = format!("hold:{}", self.me);
        let payload = seal(self.keys.as_deref(), &key, &head, state);
        let Ok(replies) = self
            .session
            .get(&key)
            .payload(payload.clone())
            .timeout(self.timeout)
            .await
        else {
            return None;
        };
        let want = format!("held:{partner}");
        while let Ok(r) = replies.recv_async().await {
            let Ok(s) = r.result() else { continue };
            let bytes = s.payload().to_bytes();
            let body = match &self.keys {
                Some(k) => k.open_handover(&[key.as_bytes(), &payload], &bytes),
                None => Some(&bytes[..]),
            };
            match body.map(|b| b.strip_prefix(want.as_bytes())) {
                Some(Some(b"")) => return Some(true),
                Some(Some(b":behind")) => return Some(false),
                _ => {}
            }
        }
        None
    }
}

/// Set a reply's acknowledgment from where the change is held (`held`, this member
/// first): acknowledged, or, with `why_not` (who did not confirm, or that nobody could),
/// in force here but not acknowledged.
pub(super) fn acknowledge(
    reply: &mut pb::ConfigReply,
    me: &str,
    held: Vec<String>,
    why_not: Option<&str>,
) {
    reply.held_by = held;
    if let Some(why) = why_not {
        reply.accepted = false;
        reply.reason = format!(
            "not acknowledged: in force on {me}, but {why}, so a takeover could lose it; \
             send the same change again"
        );
    }
}

/// Whether a change to a device whose lease stands as `holder` may be acknowledged by
/// this member, which last heard the device at `heard_ns` (Unix ns; now `now_ns`), and
/// if not, why. When the plant grants leases, only the member commanding it (holding its
/// lease, and hearing it still) acknowledges: a member cut off from the plant, or one
/// answering while the lease is vacant, could otherwise acknowledge a change that the
/// member commanding the plant never holds.
pub(super) fn may_acknowledge(
    holder: Holder,
    (heard_ns, live_ns): (u64, u64),
    now_ns: u64,
) -> Result<(), String> {
    match holder {
        Holder::Me if now_ns.saturating_sub(heard_ns) > live_ns => Err(format!(
            "the device has not been heard here for {:.1} s, so this member may no longer \
             command it",
            now_ns.saturating_sub(heard_ns) as f64 / 1e9
        )),
        Holder::Vacant => Err("the device's lease is vacant: no member commands it".into()),
        Holder::Other => Err("another member commands the device".into()),
        Holder::Me | Holder::Nobody | Holder::Unknown => Ok(()),
    }
}

/// A handover payload: `head` (a request such as `hold:{id}`), a newline, then `rest`
/// (a state, or nothing), sealed with the members' key when there are keys, bound to the
/// key it is sent on.
pub(super) fn seal(keys: Option<&Keyring>, key: &str, head: &str, rest: &[u8]) -> Vec<u8> {
    let mut bytes = Vec::with_capacity(head.len() + 1 + rest.len());
    bytes.extend_from_slice(head.as_bytes());
    bytes.push(b'\n');
    bytes.extend_from_slice(rest);
    match keys {
        Some(k) => k.seal_handover(&[key.as_bytes()], bytes),
        None => bytes,
    }
}

/// The request and what follows it in a handover payload, if it opens (with keys) and
/// its head is text; `None` for anything else (forged, altered, unsealed, garbage).
pub(super) fn open<'a>(
    keys: Option<&Keyring>,
    key: &str,
    payload: &'a [u8],
) -> Option<(&'a str, &'a [u8])> {
    let body = match keys {
        Some(k) => k.open_handover(&[key.as_bytes()], payload)?,
        None => payload,
    };
    let (head, rest) = match body.iter().position(|&b| b == b'\n') {
        Some(i) => (&body[..i], &body[i + 1..]),
        None => (body, &[][..]),
    };
    Some((std::str::from_utf8(head).ok()?, rest))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_payload_opens_only_with_the_members_key_and_on_its_own_key() {
        let ring = Keyring::new(protocol::auth::Secret::from_hex(&"ab".repeat(32)).unwrap());
        let other = Keyring::new(protocol::auth::Secret::from_hex(&"cd".repeat(32)).unwrap());
        let key = "mfc/v1/fleet/f/member/b/shard/3";
        let p = seal(Some(&ring), key, "hold:a", b"\x00state\n");
        assert_eq!(
            open(Some(&ring), key, &p),
            Some(("hold:a", &b"\x00state\n"[..]))
        );
        assert_eq!(open(Some(&other), key, &p), None, "another fleet's secret");
        assert_eq!(
            open(Some(&ring), "mfc/v1/fleet/f/member/c/shard/3", &p),
            None
        );
        assert_eq!(open(Some(&ring), key, b"hold:a\nforged"), None, "unsealed");
        let plain = seal(None, key, "release:a", &[]);
        assert_eq!(open(None, key, &plain), Some(("release:a", &[][..])));
        assert_eq!(open(None, key, b"release:a"), Some(("release:a", &[][..])));
        assert_eq!(
            open(None, key, b"\xff\xfe\n"),
            None,
            "a head that is not text"
        );
    }

    #[test]
    fn only_the_member_commanding_the_plant_acknowledges() {
        let s = 1_000_000_000;
        let live = s / 20;
        assert!(may_acknowledge(Holder::Me, (10 * s, live), 10 * s + live / 2).is_ok());
        let late = may_acknowledge(Holder::Me, (10 * s, live), 10 * s + 2 * live);
        assert!(late.is_err(), "not heard for twice the window");
        assert!(may_acknowledge(Holder::Vacant, (10 * s, live), 10 * s).is_err());
        assert!(may_acknowledge(Holder::Other, (10 * s, live), 10 * s).is_err());
        // A plant that grants no lease, or a device not heard yet: the fleet decides.
        assert!(may_acknowledge(Holder::Nobody, (0, live), 10 * s).is_ok());
        assert!(may_acknowledge(Holder::Unknown, (0, live), 10 * s).is_ok());
    }

    #[test]
    fn a_change_not_held_by_every_partner_is_not_acknowledged() {
        let mut r = pb::ConfigReply {
            accepted: true,
            ..Default::default()
        };
        acknowledge(&mut r, "a", vec!["a".into(), "b".into()], None);
        assert!(r.accepted && r.reason.is_empty());
        assert_eq!(r.held_by, ["a", "b"]);
        acknowledge(&mut r, "a", vec!["a".into()], Some("b did not confirm"));
        assert!(!r.accepted);
        assert!(r.reason.contains("in force on a, but b did not confirm"));
        assert_eq!(r.held_by, ["a"]);
    }
}

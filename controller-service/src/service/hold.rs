//! A change is acknowledged only once the members that would take the device over hold
//! it (`Fleet::partners`): the member that accepted it sends the device's new state to
//! each of them as a `hold:{id}` handover request and replies to the operator after their
//! answers. Without that, a takeover (the owner killed, paused or cut off) would carry on
//! with the state from before the change, and the operator, told "accepted", would never
//! learn that it was gone.
//!
//! The rules of the holds (one job at a time, in order; all partners asked at once; one
//! timeout) are [`crate::replication`]'s, a node that does no I/O, which the fleet's
//! simulation runs too; here is its driver: one task per member that hands it the jobs
//! and the partners' answers with the time, and carries out what it says (the queries to
//! the partners, the replies to the operators). The worker never waits: a partner that
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
use tokio::time::Instant;
use zenoh::query::Query;
use zenoh::Session;

use super::intake::Msg;
use super::keyring::Keyring;
use crate::lease::Holder;
use crate::replication::{Effect, Job, PartnerAnswer, Replication};

/// Changes waiting for their holds at most; beyond, a change is answered at once as not
/// acknowledged (the operator sends it again).
pub(super) const PENDING: usize = 256;

/// The operator's query, its payload (the reply is bound to it) and the reply as
/// accepted here (`accepted`, `reason` and `held_by` are set from the holds).
pub(super) type Answering = (Query, Vec<u8>, pb::ConfigReply);

/// One accepted change on its way to being held, or the states of the devices this
/// member commands on their way to a member that came (back) into its view; the state
/// is the devices' `encode_shard`.
pub(super) type HoldJob = Job<Answering, Vec<u8>>;

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

/// A partner's answer on its way back to the driver: the job, the partner, the answer.
type Answered = (u64, String, PartnerAnswer);

impl Replicator {
    /// Start the task that carries the holds out; it ends once the worker's queue closes
    /// and what was queued is over.
    pub(super) fn spawn(self) -> mpsc::Sender<HoldJob> {
        let (tx, rx) = mpsc::channel::<HoldJob>(PENDING);
        tokio::spawn(self.drive(rx));
        tx
    }

    async fn drive(self, mut jobs: mpsc::Receiver<HoldJob>) {
        let origin = Instant::now();
        let now = || origin.elapsed().as_nanos() as u64;
        let timeout = self.timeout.as_nanos() as u64;
        let mut node = Replication::new(timeout, PENDING);
        // Each ask sends one answer back; the asks of a job that timed out end within
        // the same timeout, so a few jobs' worth is room enough.
        let (answers_tx, mut answers) = mpsc::channel::<Answered>(64);
        let mut open = true;
        while open || !node.is_empty() {
            let deadline = node.deadline().map(|d| origin + Duration::from_nanos(d));
            tokio::select! {
                job = jobs.recv(), if open => match job {
                    Some(job) => {
                        if let Err(job) = node.submit(job, now()) {
                            self.busy(job).await;
                        }
                    }
                    None => open = false,
                },
                Some((job, partner, a)) = answers.recv() => node.answer(job, &partner, a, now()),
                _ = tokio::time::sleep_until(deadline.unwrap_or(origin)), if deadline.is_some() => {
                    node.tick(now());
                }
            }
            for effect in node.take() {
                self.carry_out(effect, &answers_tx).await;
            }
        }
    }

    async fn carry_out(
        &self,
        effect: Effect<Answering, Vec<u8>>,
        answers: &mpsc::Sender<Answered>,
    ) {
        match effect {
            Effect::Ask {
                job,
                partner,
                shard,
                state,
            } => {
                let (me, answers) = (self.clone(), answers.clone());
                tokio::spawn(async move {
                    let a = match me.hold(&partner, shard, &state).await {
                        Some(in_step) => PartnerAnswer::Held { in_step },
                        None => PartnerAnswer::Refused,
                    };
                    let _ = answers.send((job, partner, a)).await;
                });
            }
            Effect::Answer {
                answer: (query, request, mut reply),
                held,
                missing,
            } => {
                let why = (!missing.is_empty()).then(|| {
                    format!(
                        "{} did not confirm holding it within {} ms",
                        missing.join(" and "),
                        self.timeout.as_millis()
                    )
                });
                let mut by = vec![self.me.clone()];
                by.extend(held);
                acknowledge(&mut reply, &self.me, by, why.as_deref());
                self.reply(query, &request, &reply).await;
            }
            Effect::HandedOver { devices, in_step } => {
                if !in_step {
                    tracing::debug!(devices = ?devices, "devices' partners are not all in step");
                }
                let _ = self.tx.send(Msg::HandedOver { devices, in_step }).await;
            }
        }
    }

    /// A job the queue had no room for: a change is answered as not acknowledged, states
    /// sent without a change are dropped (the next change of view sends them again).
    async fn busy(&self, job: HoldJob) {
        let Some((query, request, mut reply)) = job.answer else {
            tracing::warn!(controller = %self.me, "too many changes waiting: devices' states not sent to their partners");
            return;
        };
        let busy = Some("too many changes are waiting for their partners");
        acknowledge(&mut reply, &self.me, vec![self.me.clone()], busy);
        self.reply(query, &request, &reply).await;
    }

    async fn reply(&self, query: Query, request: &[u8], reply: &pb::ConfigReply) {
        let key = query.key_expr().as_str().to_string();
        let bytes = match &self.keys {
            Some(k) => k.seal_reply(&key, request, encode(reply)),
            None => encode(reply),
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

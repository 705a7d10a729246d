//! One member's question to another (a handover request: `release:`, `copy:`, `offer:`,
//! `hold:`), as both the fleet's handovers and the holds of changes ask it: the payload
//! sealed with the members' key and bound to the key it travels on, and the answer taken
//! from the first reply that a member sealed and that the asker wants, within the
//! request's timeout. A reply from anyone else (a process with a service certificate but
//! not the fleet's secret) never counts: a forged state is never restored, a forged
//! "held" never acknowledges a change.
//!
//! The waiting is [`first_wanted`], over any source of replies ([`Replies`]): Zenoh's in
//! the service, a channel fed in tokio's paused clock in the tests below, so the timeout
//! that bounds a handover is tested in virtual time, without a network or a race.

use std::future::Future;
use std::time::Duration;

use zenoh::Session;

use super::keyring::Keyring;

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

/// Where a question's replies come from, in the order they come; `None` once no more
/// will (the query is over).
pub(super) trait Replies: Send {
    /// The next good reply's payload (error replies are skipped by the source).
    fn next(&mut self) -> impl Future<Output = Option<Vec<u8>>> + Send;
}

impl Replies for zenoh::handlers::FifoChannelHandler<zenoh::query::Reply> {
    async fn next(&mut self) -> Option<Vec<u8>> {
        while let Ok(r) = self.recv_async().await {
            if let Ok(s) = r.result() {
                return Some(s.payload().to_bytes().into_owned());
            }
        }
        None
    }
}

/// The first reply that `take` takes, of those that come within `timeout`; `None` if the
/// replies end or the time is up first. The timeout is this function's own, whatever
/// the source does: a member that keeps sending replies nobody wants cannot hold the
/// asker past it.
pub(super) async fn first_wanted<T>(
    mut replies: impl Replies,
    timeout: Duration,
    mut take: impl FnMut(&[u8]) -> Option<T> + Send,
) -> Option<T> {
    let wait = async {
        while let Some(bytes) = replies.next().await {
            if let Some(t) = take(&bytes) {
                return Some(t);
            }
        }
        None
    };
    tokio::time::timeout(timeout, wait).await.ok().flatten()
}

/// Ask the member on `key` (through `session`, sealing with `keys` when there are): the
/// request `head` followed by `rest`; the answer is what `take` makes of the first reply
/// a member sealed (opened), within `timeout`, or `None`.
pub(super) async fn ask_member<T>(
    (session, keys, key): (&Session, Option<&Keyring>, &str),
    (head, rest): (&str, &[u8]),
    timeout: Duration,
    mut take: impl FnMut(&[u8]) -> Option<T> + Send,
) -> Option<T> {
    let payload = seal(keys, key, head, rest);
    let asked = session.get(key).payload(payload.clone()).timeout(timeout);
    let replies = asked.await.ok()?;
    first_wanted(replies, timeout, |bytes| {
        let body = match keys {
            Some(k) => k.open_handover(&[key.as_bytes(), &payload], bytes),
            None => Some(bytes),
        };
        match body {
            Some(b) => take(b),
            None => {
                tracing::warn!(key = %key, "a handover answer not sealed by a member: ignored");
                None
            }
        }
    })
    .await
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::sync::mpsc;
    use tokio::time::Instant;

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

    /// Replies that come at the given times (ms after the start), from a task that
    /// sends them into a channel; the channel closes after the last.
    struct Timed(mpsc::Receiver<Vec<u8>>);

    impl Timed {
        fn start(plan: &[(u64, &str)]) -> Self {
            let (tx, rx) = mpsc::channel(16);
            let origin = Instant::now();
            let plan: Vec<(u64, Vec<u8>)> = plan
                .iter()
                .map(|(ms, s)| (*ms, s.as_bytes().to_vec()))
                .collect();
            tokio::spawn(async move {
                for (ms, bytes) in plan {
                    tokio::time::sleep_until(origin + Duration::from_millis(ms)).await;
                    if tx.send(bytes).await.is_err() {
                        return;
                    }
                }
                // Keep the query open, as a source whose peers stay silent does.
                tokio::time::sleep(Duration::from_secs(3600)).await;
            });
            Self(rx)
        }
    }

    impl Replies for Timed {
        async fn next(&mut self) -> Option<Vec<u8>> {
            self.0.recv().await
        }
    }

    /// The answer and when it came (ms), `take` wanting replies that start with "held".
    async fn ask(plan: &[(u64, &str)], timeout_ms: u64) -> (Option<String>, u64) {
        let origin = Instant::now();
        let got = first_wanted(Timed::start(plan), Duration::from_millis(timeout_ms), |b| {
            b.starts_with(b"held")
                .then(|| String::from_utf8_lossy(b).into_owned())
        })
        .await;
        (got, origin.elapsed().as_millis() as u64)
    }

    #[tokio::test(start_paused = true)]
    async fn the_first_wanted_reply_is_the_answer_and_it_ends_the_wait() {
        let plan = [(20, "garbage"), (50, "held:b"), (80, "held:c")];
        assert_eq!(ask(&plan, 500).await, (Some("held:b".into()), 50));
    }

    #[tokio::test(start_paused = true)]
    async fn replies_nobody_wants_do_not_hold_the_asker_past_its_timeout() {
        let plan: Vec<(u64, &str)> = (1..=100).map(|i| (i * 10, "refused")).collect();
        assert_eq!(ask(&plan, 250).await, (None, 250));
    }

    #[tokio::test(start_paused = true)]
    async fn a_wanted_reply_after_the_timeout_counts_for_nothing() {
        assert_eq!(ask(&[(300, "held:b")], 250).await, (None, 250));
    }

    #[tokio::test(start_paused = true)]
    async fn replies_that_end_without_a_wanted_one_end_the_wait_at_once() {
        let (tx, rx) = mpsc::channel(4);
        tx.send(b"no".to_vec()).await.unwrap();
        drop(tx);
        let origin = Instant::now();
        let got = first_wanted(Timed(rx), Duration::from_millis(500), |_| None::<()>).await;
        assert_eq!((got, origin.elapsed().as_millis()), (None, 0));
    }
}

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

use std::future::Future;
use std::sync::Arc;
use std::time::Duration;

use protocol::{encode, keys, pb};
use tokio::sync::mpsc;
use tokio::time::Instant;
use zenoh::query::Query;
use zenoh::Session;

use super::ask::ask_member;
use super::core::Shared;
use super::intake::Msg;
use super::keyring::Keyring;
use super::locks::lock;
use crate::lease::Holder;
use crate::replication::{Effect, Job, PartnerAnswer, Replication};

/// Changes waiting for their holds at most; beyond, a change is answered at once as not
/// acknowledged (the operator sends it again).
pub(super) const PENDING: usize = 256;

/// An accepted change's operator, to be answered once its holds are over.
pub(super) struct Answering {
    pub(super) query: Query,
    /// The query's payload: the reply is bound to it.
    pub(super) request: Vec<u8>,
    /// The reply as accepted here (`accepted`, `reason` and `held_by` are set from the
    /// holds).
    pub(super) reply: pb::ConfigReply,
    /// The device changed: whether this member may still acknowledge is asked again
    /// when the holds end.
    pub(super) device: String,
    /// Who held its lease, as this member saw it, when the change was accepted.
    pub(super) holder: Holder,
}

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
    /// The worker's state: whether this member still commands a device when its
    /// change's holds end ([`crate::Registry::may_still_acknowledge`]).
    pub(super) shared: Arc<Shared>,
}

/// A partner's answer on its way back to the driver: the job, the partner, the answer.
type Answered = (u64, String, PartnerAnswer);

/// What the holds' driver does outside itself. The service's is [`Replicator`] (a Zenoh
/// query per partner, the operator's sealed reply, the worker's queue); the tests below
/// give the driver partners that answer in tokio's paused, virtual time, so the wiring's
/// own timer (one per job, the node's deadline) is tested without a network or a race.
pub(super) trait Partners: Send + Sync + 'static {
    /// What an operator is answered with; the driver carries it through untouched.
    type Answering: Send + 'static;
    /// Ask `partner` to hold `state`. It ends with the partner's answer; a query that
    /// ends without one (its own timeout included) is [`PartnerAnswer::Refused`].
    fn ask(
        &self,
        partner: String,
        shard: u32,
        state: Vec<u8>,
    ) -> impl Future<Output = PartnerAnswer> + Send;
    /// Answer the operator: the change is in force here and held by `held` (the
    /// partners that confirmed); acknowledged unless `why_not`.
    fn answer(
        &self,
        to: Self::Answering,
        held: Vec<String>,
        why_not: Option<String>,
    ) -> impl Future<Output = ()> + Send;
    /// States sent without a change are over: `in_step` if every partner holds them and
    /// is in step with this member.
    fn handed_over(&self, devices: Vec<String>, in_step: bool) -> impl Future<Output = ()> + Send;
}

/// Why a change waits no more: the queue of holds had no room for it.
pub(super) const BUSY: &str = "too many changes are waiting for their partners";

/// The holds' driver: it hands the node ([`Replication`]) the jobs and the partners'
/// answers with the time, sleeps until the node's deadline, and carries out what the
/// node says, each ask in a task of its own (a silent partner holds up no other). It
/// ends once `jobs` is closed and every job taken is over.
pub(super) async fn drive<P: Partners>(
    io: Arc<P>,
    timeout: Duration,
    mut jobs: mpsc::Receiver<Job<P::Answering, Vec<u8>>>,
) {
    let origin = Instant::now();
    let now = || origin.elapsed().as_nanos() as u64;
    let mut node = Replication::new(timeout.as_nanos() as u64, PENDING);
    // Each ask sends one answer back; the asks of a job that timed out end within the
    // same timeout, so a few jobs' worth is room enough.
    let (answers_tx, mut answers) = mpsc::channel::<Answered>(64);
    let mut open = true;
    while open || !node.is_empty() {
        let deadline = node.deadline().map(|d| origin + Duration::from_nanos(d));
        tokio::select! {
            job = jobs.recv(), if open => match job {
                Some(job) => {
                    if let Err(job) = node.submit(job, now()) {
                        busy(&*io, job).await;
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
            carry_out(&io, timeout, effect, &answers_tx).await;
        }
    }
}

async fn carry_out<P: Partners>(
    io: &Arc<P>,
    timeout: Duration,
    effect: Effect<P::Answering, Vec<u8>>,
    answers: &mpsc::Sender<Answered>,
) {
    match effect {
        Effect::Ask {
            job,
            partner,
            shard,
            state,
        } => {
            let (io, answers) = (io.clone(), answers.clone());
            tokio::spawn(async move {
                let a = io.ask(partner.clone(), shard, state).await;
                let _ = answers.send((job, partner, a)).await;
            });
        }
        Effect::Answer {
            answer,
            held,
            missing,
        } => {
            let why = (!missing.is_empty()).then(|| {
                format!(
                    "{} did not confirm holding it within {} ms",
                    missing.join(" and "),
                    timeout.as_millis()
                )
            });
            io.answer(answer, held, why).await;
        }
        Effect::HandedOver { devices, in_step } => io.handed_over(devices, in_step).await,
    }
}

/// A job the queue had no room for: a change is answered as not acknowledged, states
/// sent without a change are dropped (the next change of view sends them again).
async fn busy<P: Partners>(io: &P, job: Job<P::Answering, Vec<u8>>) {
    match job.answer {
        Some(to) => io.answer(to, Vec::new(), Some(BUSY.into())).await,
        None => {
            tracing::warn!("too many changes waiting: devices' states not sent to their partners")
        }
    }
}

impl Replicator {
    /// Start the task that carries the holds out; it ends once the worker's queue closes
    /// and what was queued is over.
    pub(super) fn spawn(self) -> mpsc::Sender<HoldJob> {
        let (tx, rx) = mpsc::channel::<HoldJob>(PENDING);
        let timeout = self.timeout;
        tokio::spawn(drive(Arc::new(self), timeout, rx));
        tx
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
        let want = format!("held:{partner}");
        let query = (&self.session, self.keys.as_deref(), key.as_str());
        ask_member(query, (&head, state), self.timeout, |body| {
            match body.strip_prefix(want.as_bytes()) {
                Some(b"") => Some(true),
                Some(b":behind") => Some(false),
                _ => None,
            }
        })
        .await
    }
}

impl Partners for Replicator {
    type Answering = Answering;

    async fn ask(&self, partner: String, shard: u32, state: Vec<u8>) -> PartnerAnswer {
        match self.hold(&partner, shard, &state).await {
            Some(in_step) => PartnerAnswer::Held { in_step },
            None => PartnerAnswer::Refused,
        }
    }

    async fn answer(&self, to: Answering, held: Vec<String>, why_not: Option<String>) {
        let Answering {
            query,
            request,
            mut reply,
            device,
            holder,
        } = to;
        // The lease may have moved while the partners were asked (this job may have
        // waited behind another's timeout): a member that no longer commands the device
        // must not say "acknowledged" for a change the new holder may not have.
        let why_not = why_not.or_else(|| {
            let c = lock(&self.shared.core);
            let now = c
                .registry
                .may_still_acknowledge(&device, holder, protocol::unix_ns());
            now.err()
                .map(|why| format!("by the time its partners held it, {why}"))
        });
        let mut by = vec![self.me.clone()];
        by.extend(held);
        acknowledge(&mut reply, &self.me, by, why_not.as_deref());
        self.reply(query, &request, &reply).await;
    }

    async fn handed_over(&self, devices: Vec<String>, in_step: bool) {
        if !in_step {
            tracing::debug!(devices = ?devices, "devices' partners are not all in step");
        }
        let _ = self.tx.send(Msg::HandedOver { devices, in_step }).await;
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

#[cfg(test)]
mod tests {
    use super::*;

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

    /// The driver in tokio's paused clock: virtual time moves only when every task
    /// waits, straight to the next timer, so the times below are exact, on any machine.
    mod in_virtual_time {
        use super::*;
        use std::sync::Mutex;

        /// What the driver did.
        #[derive(Debug, Clone, PartialEq)]
        enum Did {
            /// It asked `partner` to hold the job whose state is `plan`.
            Ask {
                partner: String,
                plan: String,
            },
            Answer {
                change: u32,
                held: Vec<String>,
                why_not: Option<String>,
            },
            HandedOver {
                devices: Vec<String>,
                in_step: bool,
            },
        }

        /// Partners that answer as the asked state says, per partner: `b=held:100`
        /// (holds it after 100 ms), `b=behind:100` (holds it, not in step),
        /// `b=refused:100`; a partner not named never answers.
        struct Fake {
            origin: Instant,
            log: Mutex<Vec<(u64, Did)>>,
        }

        impl Fake {
            fn did(&self, what: Did) {
                let ms = self.origin.elapsed().as_millis() as u64;
                self.log.lock().unwrap().push((ms, what));
            }
        }

        impl Partners for Fake {
            type Answering = u32;

            async fn ask(&self, partner: String, _shard: u32, state: Vec<u8>) -> PartnerAnswer {
                let plan = String::from_utf8(state).unwrap();
                self.did(Did::Ask {
                    partner: partner.clone(),
                    plan: plan.clone(),
                });
                let mine = format!("{partner}=");
                let Some(word) = plan.split(' ').find_map(|w| w.strip_prefix(mine.as_str())) else {
                    return std::future::pending().await;
                };
                let (how, ms) = word.split_once(':').unwrap();
                tokio::time::sleep(Duration::from_millis(ms.parse().unwrap())).await;
                match how {
                    "held" => PartnerAnswer::Held { in_step: true },
                    "behind" => PartnerAnswer::Held { in_step: false },
                    _ => PartnerAnswer::Refused,
                }
            }

            async fn answer(&self, change: u32, held: Vec<String>, why_not: Option<String>) {
                self.did(Did::Answer {
                    change,
                    held,
                    why_not,
                });
            }

            async fn handed_over(&self, devices: Vec<String>, in_step: bool) {
                self.did(Did::HandedOver { devices, in_step });
            }
        }

        fn names(xs: &[&str]) -> Vec<String> {
            xs.iter().map(|x| x.to_string()).collect()
        }

        fn change(n: u32, plan: &str, partners: &[&str]) -> Job<u32, Vec<u8>> {
            Job {
                answer: Some(n),
                shard: 1,
                state: plan.as_bytes().to_vec(),
                partners: names(partners),
                devices: Vec::new(),
            }
        }

        fn ask(partner: &str, plan: &str) -> Did {
            Did::Ask {
                partner: partner.into(),
                plan: plan.into(),
            }
        }

        fn answered(change: u32, held: &[&str], why_not: Option<&str>) -> Did {
            Did::Answer {
                change,
                held: names(held),
                why_not: why_not.map(String::from),
            }
        }

        /// Drive `jobs` (queued at once, then the queue closed) with `timeout_ms`: what
        /// was done and when, and when the driver ended (ms).
        async fn run(jobs: Vec<Job<u32, Vec<u8>>>, timeout_ms: u64) -> (Vec<(u64, Did)>, u64) {
            let fake = Arc::new(Fake {
                origin: Instant::now(),
                log: Mutex::new(Vec::new()),
            });
            let (tx, rx) = mpsc::channel(PENDING);
            let task = tokio::spawn(drive(fake.clone(), Duration::from_millis(timeout_ms), rx));
            for job in jobs {
                tx.send(job).await.unwrap();
            }
            drop(tx);
            task.await.unwrap();
            let ended = fake.origin.elapsed().as_millis() as u64;
            let log = fake.log.lock().unwrap().clone();
            (log, ended)
        }

        #[tokio::test(start_paused = true)]
        async fn every_partner_is_asked_at_once_and_the_change_acknowledged_when_the_last_holds_it()
        {
            let plan = "b=held:100 c=held:300";
            let (log, ended) = run(vec![change(1, plan, &["b", "c"])], 500).await;
            assert_eq!(
                log,
                [
                    (0, ask("b", plan)),
                    (0, ask("c", plan)),
                    (300, answered(1, &["b", "c"], None)),
                ]
            );
            assert_eq!(ended, 300, "the driver ends with the last job");
        }

        #[tokio::test(start_paused = true)]
        async fn silent_partners_cost_one_timeout_together_and_the_change_is_not_acknowledged() {
            let plan = "b=held:100";
            let (log, _) = run(vec![change(1, plan, &["b", "c", "d"])], 500).await;
            let why = "c and d did not confirm holding it within 500 ms";
            assert_eq!(log.last(), Some(&(500, answered(1, &["b"], Some(why)))));
            assert_eq!(log.len(), 4, "three asks and the answer: {log:?}");
        }

        #[tokio::test(start_paused = true)]
        async fn a_refusal_ends_the_wait_for_that_partner_at_once() {
            let plan = "b=held:100 c=refused:50";
            let (log, _) = run(vec![change(1, plan, &["b", "c"])], 500).await;
            let why = "c did not confirm holding it within 500 ms";
            assert_eq!(log.last(), Some(&(100, answered(1, &["b"], Some(why)))));
        }

        #[tokio::test(start_paused = true)]
        async fn jobs_go_one_at_a_time_in_order_and_a_late_answer_counts_for_none() {
            let (first, second) = ("b=held:700", "c=held:100");
            let jobs = vec![change(1, first, &["b"]), change(2, second, &["b"])];
            let (log, ended) = run(jobs, 500).await;
            let why = "b did not confirm holding it within 500 ms";
            // b's answer to the first job comes at 700 ms, while the second waits on b
            // (which holds up nothing of its own: it never answers the second).
            assert_eq!(
                log,
                [
                    (0, ask("b", first)),
                    (500, answered(1, &[], Some(why))),
                    (500, ask("b", second)),
                    (1000, answered(2, &[], Some(why))),
                ]
            );
            assert_eq!(ended, 1000);
        }

        #[tokio::test(start_paused = true)]
        async fn states_sent_without_a_change_say_whether_every_partner_is_in_step() {
            let states = |plan: &str| Job {
                answer: None,
                shard: 1,
                state: plan.as_bytes().to_vec(),
                partners: names(&["b", "c"]),
                devices: names(&["rig"]),
            };
            let jobs = vec![
                states("b=held:10 c=behind:20"),
                states("b=held:10 c=held:30"),
            ];
            let (log, _) = run(jobs, 500).await;
            let over: Vec<_> = log
                .into_iter()
                .filter(|(_, d)| matches!(d, Did::HandedOver { .. }))
                .collect();
            let handed = |in_step| Did::HandedOver {
                devices: names(&["rig"]),
                in_step,
            };
            assert_eq!(over, [(20, handed(false)), (50, handed(true))]);
        }

        #[tokio::test(start_paused = true)]
        async fn a_change_beyond_a_full_queue_is_answered_at_once_as_not_acknowledged() {
            // The first job under way, PENDING behind it, and one more: that one is busy.
            let jobs = (0..PENDING as u32 + 2)
                .map(|n| change(n, "", &["b"]))
                .collect();
            let (log, ended) = run(jobs, 10).await;
            let answers: Vec<_> = log
                .into_iter()
                .filter_map(|(t, d)| match d {
                    Did::Answer {
                        change, why_not, ..
                    } => Some((t, change, why_not)),
                    _ => None,
                })
                .collect();
            let busy = PENDING as u32 + 1;
            assert_eq!(answers[0], (0, busy, Some(BUSY.to_string())));
            let rest: Vec<_> = answers[1..].iter().map(|a| (a.0, a.1)).collect();
            let expected: Vec<_> = (0..=PENDING as u32)
                .map(|n| (10 * (u64::from(n) + 1), n))
                .collect();
            assert_eq!(rest, expected, "the others in order, one timeout each");
            assert_eq!(ended, 10 * (PENDING as u64 + 1));
        }
    }
}

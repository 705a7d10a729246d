//! The holds of changes, as a node that does no I/O: which partner to ask to hold which
//! state, when a change may be acknowledged, and when to give up on a partner.
//!
//! A change is acknowledged only once the members that would take its device over hold
//! it (`Fleet::partners`): without that, a takeover would carry on with the state from
//! before the change, and the operator, told "accepted", would never learn it was gone.
//! The same queue carries the states a member that commands devices sends to a member
//! that came (back) into its view, so that its partners end in step with it.
//!
//! The rules, which the service's hold task (`service/hold.rs`) and the fleet's
//! simulation (`tests/tests/lease_sim.rs`) both run:
//! * one job at a time, in the order submitted: two quick changes to one device reach a
//!   partner in that order, so a partner never ends holding the older one;
//! * a job asks all its partners at once, and ends when each answered or when its time
//!   is up, whichever comes first: one silent partner costs one timeout, not one per
//!   partner, and the jobs behind it wait no longer than that;
//! * a job's outcome names who holds it and who did not; it is acknowledged only when
//!   every partner holds it;
//! * at most `capacity` jobs wait: beyond, [`Replication::submit`] hands the job back,
//!   and the caller answers at once that the change is not acknowledged.
//!
//! Time is passed in (ns, from any origin that only goes forward); what to do comes back
//! from [`Replication::take`], for the caller to carry out.

use std::collections::VecDeque;

/// A job: a change to be held (`answer`: what to answer the operator with), or states
/// sent without a change (`answer` none), to `partners`.
#[derive(Debug, Clone, PartialEq)]
pub struct Job<A, S> {
    pub answer: Option<A>,
    pub shard: u32,
    /// What the partners are asked to hold (the devices' state, `encode_shard`).
    pub state: S,
    pub partners: Vec<String>,
    /// For states sent without a change: the devices, whose holder learns whether its
    /// partners are in step with it ([`Effect::HandedOver`]).
    pub devices: Vec<String>,
}

/// A partner's answer to a hold.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PartnerAnswer {
    /// It holds the state; `in_step`: it is also in step with the sender's lease.
    Held { in_step: bool },
    /// It refused, or its query ended with no answer that says it holds the state.
    Refused,
}

/// What the caller carries out.
#[derive(Debug, Clone, PartialEq)]
pub enum Effect<A, S> {
    /// Ask `partner` to hold `state`; its answer comes back through
    /// [`Replication::answer`] with `job`.
    Ask {
        job: u64,
        partner: String,
        shard: u32,
        state: S,
    },
    /// A change's holds are over: answer the operator. `missing` (in the job's order)
    /// did not confirm holding it; acknowledged if it is empty.
    Answer {
        answer: A,
        held: Vec<String>,
        missing: Vec<String>,
    },
    /// States sent without a change are over: `in_step` if every partner holds them and
    /// is in step with this member.
    HandedOver { devices: Vec<String>, in_step: bool },
}

/// The job being carried out.
#[derive(Debug)]
struct Head<A, S> {
    id: u64,
    job: Job<A, S>,
    /// When its asks left, ns.
    started: u64,
    /// Each partner's answer, in the job's order (`None`: none yet).
    answers: Vec<Option<PartnerAnswer>>,
}

/// One member's holds: a queue of jobs, carried out one at a time.
#[derive(Debug)]
pub struct Replication<A, S> {
    timeout_ns: u64,
    capacity: usize,
    waiting: VecDeque<Job<A, S>>,
    head: Option<Head<A, S>>,
    next_id: u64,
    out: Vec<Effect<A, S>>,
}

impl<A, S: Clone> Replication<A, S> {
    /// Holds that give a partner `timeout_ns` to answer, with at most `capacity` jobs
    /// waiting behind the one carried out.
    pub fn new(timeout_ns: u64, capacity: usize) -> Self {
        Self {
            timeout_ns,
            capacity,
            waiting: VecDeque::new(),
            head: None,
            next_id: 1,
            out: Vec::new(),
        }
    }

    /// Queue `job`; it starts at once if nothing else is carried out. A full queue hands
    /// it back.
    pub fn submit(&mut self, job: Job<A, S>, now_ns: u64) -> Result<(), Job<A, S>> {
        if self.waiting.len() >= self.capacity {
            return Err(job);
        }
        self.waiting.push_back(job);
        self.advance(now_ns);
        Ok(())
    }

    /// `partner`'s answer to job `job`. An answer to a job that is over, from a member
    /// not asked, or a second one from the same partner changes nothing.
    pub fn answer(&mut self, job: u64, partner: &str, answer: PartnerAnswer, now_ns: u64) {
        let Some(head) = self.head.as_mut().filter(|h| h.id == job) else {
            return;
        };
        if let Some(i) = head.job.partners.iter().position(|p| p == partner) {
            head.answers[i].get_or_insert(answer);
        }
        self.advance(now_ns);
    }

    /// Let time pass: a job whose time is up ends with the answers it has.
    pub fn tick(&mut self, now_ns: u64) {
        self.advance(now_ns);
    }

    /// When [`Replication::tick`] next has something to do, if anything waits.
    pub fn deadline(&self) -> Option<u64> {
        self.head
            .as_ref()
            .map(|h| h.started.saturating_add(self.timeout_ns))
    }

    /// Jobs submitted and not over, the one carried out included.
    pub fn len(&self) -> usize {
        self.waiting.len() + usize::from(self.head.is_some())
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// What to carry out, in order.
    pub fn take(&mut self) -> Vec<Effect<A, S>> {
        std::mem::take(&mut self.out)
    }

    /// End the head if it is over, and start the next job, until one is under way.
    fn advance(&mut self, now_ns: u64) {
        loop {
            if let Some(head) = &self.head {
                let answered = head.answers.iter().all(Option::is_some);
                let late = now_ns >= head.started.saturating_add(self.timeout_ns);
                if !answered && !late {
                    return;
                }
                let head = self.head.take().expect("a head");
                self.out.push(outcome(head));
            }
            let Some(job) = self.waiting.pop_front() else {
                return;
            };
            self.start(job, now_ns);
        }
    }

    fn start(&mut self, job: Job<A, S>, now_ns: u64) {
        let id = self.next_id;
        self.next_id += 1;
        for p in &job.partners {
            self.out.push(Effect::Ask {
                job: id,
                partner: p.clone(),
                shard: job.shard,
                state: job.state.clone(),
            });
        }
        self.head = Some(Head {
            id,
            answers: vec![None; job.partners.len()],
            job,
            started: now_ns,
        });
    }
}

/// What an ended job comes to.
fn outcome<A, S>(head: Head<A, S>) -> Effect<A, S> {
    let mut held = Vec::new();
    let mut missing = Vec::new();
    let mut in_step = true;
    for (p, a) in head.job.partners.into_iter().zip(head.answers) {
        match a {
            Some(PartnerAnswer::Held { in_step: s }) => {
                held.push(p);
                in_step &= s;
            }
            _ => missing.push(p),
        }
    }
    match head.job.answer {
        Some(answer) => Effect::Answer {
            answer,
            held,
            missing,
        },
        None => Effect::HandedOver {
            devices: head.job.devices,
            in_step: in_step && missing.is_empty(),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: u64 = 1_000_000;

    fn change(n: u32, partners: &[&str]) -> Job<u32, &'static str> {
        Job {
            answer: Some(n),
            shard: 3,
            state: "state",
            partners: partners.iter().map(|p| p.to_string()).collect(),
            devices: Vec::new(),
        }
    }

    fn asks(effects: &[Effect<u32, &str>]) -> Vec<(u64, String)> {
        effects
            .iter()
            .filter_map(|e| match e {
                Effect::Ask { job, partner, .. } => Some((*job, partner.clone())),
                _ => None,
            })
            .collect()
    }

    #[test]
    fn a_change_is_acknowledged_once_every_partner_holds_it() {
        let mut r = Replication::new(500 * MS, 8);
        r.submit(change(1, &["b", "c"]), 0).unwrap();
        assert_eq!(asks(&r.take()), [(1, "b".into()), (1, "c".into())]);
        r.answer(1, "b", PartnerAnswer::Held { in_step: true }, 3 * MS);
        assert!(r.take().is_empty(), "c has not answered");
        r.answer(1, "c", PartnerAnswer::Held { in_step: false }, 4 * MS);
        let done = r.take();
        assert_eq!(
            done,
            [Effect::Answer {
                answer: 1,
                held: vec!["b".into(), "c".into()],
                missing: vec![]
            }]
        );
        assert!(r.is_empty() && r.deadline().is_none());
    }

    #[test]
    fn one_silent_partner_costs_one_timeout_and_is_named() {
        let mut r = Replication::new(500 * MS, 8);
        r.submit(change(1, &["b", "c"]), 10 * MS).unwrap();
        r.take();
        r.answer(1, "c", PartnerAnswer::Held { in_step: true }, 12 * MS);
        assert_eq!(r.deadline(), Some(510 * MS));
        r.tick(509 * MS);
        assert!(r.take().is_empty(), "not yet");
        r.tick(510 * MS);
        assert_eq!(
            r.take(),
            [Effect::Answer {
                answer: 1,
                held: vec!["c".into()],
                missing: vec!["b".into()]
            }]
        );
    }

    #[test]
    fn jobs_go_one_at_a_time_in_order() {
        let mut r = Replication::new(500 * MS, 8);
        r.submit(change(1, &["b"]), 0).unwrap();
        r.submit(change(2, &["b"]), MS).unwrap();
        assert_eq!(asks(&r.take()), [(1, "b".into())], "the second waits");
        // A late or stray answer changes nothing.
        r.answer(2, "b", PartnerAnswer::Held { in_step: true }, 2 * MS);
        r.answer(1, "z", PartnerAnswer::Held { in_step: true }, 2 * MS);
        assert!(r.take().is_empty());
        r.answer(1, "b", PartnerAnswer::Refused, 3 * MS);
        let e = r.take();
        assert_eq!(e.len(), 2, "{e:?}");
        assert!(matches!(&e[0], Effect::Answer { answer: 1, missing, .. } if missing == &["b"]));
        assert_eq!(asks(&e[1..]), [(2, "b".into())]);
        // The refused job's answer, sent again late, does not count for the next one.
        r.answer(1, "b", PartnerAnswer::Held { in_step: true }, 4 * MS);
        assert!(r.take().is_empty());
        assert_eq!(
            r.deadline(),
            Some(503 * MS),
            "the second's time runs from its start"
        );
    }

    #[test]
    fn the_first_answer_of_a_partner_counts() {
        let mut r = Replication::new(500 * MS, 8);
        r.submit(change(1, &["b", "c"]), 0).unwrap();
        r.take();
        r.answer(1, "b", PartnerAnswer::Refused, MS);
        r.answer(1, "b", PartnerAnswer::Held { in_step: true }, MS);
        r.answer(1, "c", PartnerAnswer::Held { in_step: true }, MS);
        assert!(matches!(&r.take()[..], [Effect::Answer { missing, .. }] if missing == &["b"]));
    }

    #[test]
    fn states_sent_without_a_change_say_whether_the_partners_are_in_step() {
        let mut r: Replication<u32, &str> = Replication::new(500 * MS, 8);
        let job = |partners: &[&str]| Job {
            answer: None,
            shard: 1,
            state: "s",
            partners: partners.iter().map(|p| p.to_string()).collect(),
            devices: vec!["d".into()],
        };
        r.submit(job(&["b", "c"]), 0).unwrap();
        r.answer(1, "b", PartnerAnswer::Held { in_step: true }, MS);
        r.answer(1, "c", PartnerAnswer::Held { in_step: false }, MS);
        r.submit(job(&["b"]), MS).unwrap();
        r.answer(2, "b", PartnerAnswer::Held { in_step: true }, MS);
        r.submit(job(&["b"]), MS).unwrap();
        r.tick(600 * MS);
        let over: Vec<bool> = r
            .take()
            .into_iter()
            .filter_map(|e| match e {
                Effect::HandedOver { in_step, devices } => {
                    assert_eq!(devices, ["d"]);
                    Some(in_step)
                }
                _ => None,
            })
            .collect();
        assert_eq!(over, [false, true, false], "behind, in step, silent");
    }

    #[test]
    fn a_full_queue_hands_the_job_back_and_a_job_with_no_partner_ends_at_once() {
        let mut r = Replication::new(500 * MS, 2);
        r.submit(change(1, &["b"]), 0).unwrap();
        r.submit(change(2, &["b"]), 0).unwrap();
        r.submit(change(3, &["b"]), 0).unwrap();
        assert_eq!(r.len(), 3, "one under way and two waiting");
        assert_eq!(r.submit(change(4, &["b"]), 0).unwrap_err().answer, Some(4));
        let mut s = Replication::new(500 * MS, 2);
        s.submit(change(9, &[]), 0).unwrap();
        assert_eq!(
            s.take(),
            [Effect::Answer {
                answer: 9,
                held: vec![],
                missing: vec![]
            }]
        );
    }
}

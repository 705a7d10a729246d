//! Operators' changes, from the request to the reply. A change (configuration, envelope,
//! reference, commissioning) goes through five steps, and the operator hears only at the
//! end:
//! 1. it waits while another change of its device is being written
//!    ([`crate::changes::Serial`]): each is decided on the state the one before it left;
//! 2. it is decided ([`super::core::Core::decide`], in [`super::change`]): who asks must be allowed ([`crate::access`]), the
//!    audit file must have room for its record, and the registry tries it
//!    ([`crate::Registry::trial`]): refused, or the state it would leave;
//! 3. its record goes to the audit file ([`crate::trail`]): the decision and, if accepted,
//!    that state ([`crate::journal`]); nothing is in force yet;
//! 4. once the record is durable, the change is made ([`super::core::Core::commit`]) and must leave the
//!    state recorded, or it is withdrawn (recorded too); a record that could not be written
//!    refuses its change, and nothing changed;
//! 5. the reply goes out, at once or once the fleet's partners hold the change
//!    ([`super::hold`]).
//!
//! Without an audit file, steps 3 and 4 are one: the change is in force at once, and its
//! reply says that it is not durable (`ConfigReply.durable`).

use protocol::{encode, pb, printable};
use tokio::sync::mpsc;

use super::change::{Change, Decision, Tried, Waiting};
use super::locks::lock;
use super::worker::Worker;
use crate::changes::Arrival;
use crate::journal::{Record, State, Write};
use crate::trail::{NotWritten, Pending, Written};

impl Worker {
    /// A change arrives: decided now, or queued behind its device's change being written,
    /// or refused if too many wait.
    pub(super) async fn submit(&mut self, c: Change) {
        let dev = c.dev.clone();
        match self.changes.serial.arrive(&dev, c) {
            Arrival::Now(c) => self.run_changes(c).await,
            Arrival::Queued => {}
            Arrival::Full(c, n) => {
                let why = format!("{n} changes of this device wait to be written; nothing changed, send it again later");
                let reply = lock(&self.shared.core).registry.refuse_request(&dev, why);
                self.respond(c, reply).await;
            }
        }
    }

    /// Decide `first` and, while each is done at once (no audit file, or refused without
    /// a record), the changes of its device that wait behind it.
    pub(super) async fn run_changes(&mut self, first: Change) {
        let mut next = Some(first);
        while let Some(c) = next {
            next = self.begin(c).await;
        }
    }

    /// Decide one change and hand its record to the writer; the next change of its
    /// device to decide, if this one is done already.
    pub(super) async fn begin(&mut self, c: Change) -> Option<Change> {
        let (decision, permit) = lock(&self.shared.core).decide(&c);
        let dev = c.dev.clone();
        match decision {
            Decision::NoRoom(reply) => {
                self.respond(c, reply).await;
                self.changes.serial.done(&dev)
            }
            Decision::Refused(refused) => {
                let (reply, entry) = *refused;
                match permit {
                    Some(p) => {
                        let w = Write::Record(Record { entry, state: None });
                        self.wait_for(p, w, Waiting::Refusal(c, reply));
                    }
                    None => self.respond(c, reply).await,
                }
                self.changes.serial.done(&dev)
            }
            Decision::Tried(t) => match permit {
                Some(p) => {
                    let state = self.state_to_keep(&dev, &t.trial.after);
                    let w = Write::Record(Record {
                        entry: t.entry.clone(),
                        state: Some(state),
                    });
                    self.wait_for(p, w, Waiting::Tried(c, t));
                    None
                }
                None => {
                    self.finish_tried(c, &t, Ok(())).await;
                    self.changes.serial.done(&dev)
                }
            },
        }
    }

    /// The state a record keeps: what the change leaves, and the file's configuration.
    pub(super) fn state_to_keep(
        &self,
        dev: &str,
        after: &(pb::DeviceConfig, crate::lease::Version),
    ) -> State {
        let file = lock(&self.shared.core).registry.file_config_of(dev);
        State {
            config: after.0.clone(),
            version: after.1,
            file: file.unwrap_or_else(|| after.0.clone()),
        }
    }

    /// Send a record to the writer and remember what waits for it.
    pub(super) fn wait_for(&mut self, permit: mpsc::OwnedPermit<Pending>, w: Write, then: Waiting) {
        let id = self.changes.next;
        self.changes.next += 1;
        self.changes.waiting.insert(id, then);
        permit.send((w, Some((id, self.changes.written.clone()))));
    }

    /// The writer's word on one of this worker's records.
    pub(super) async fn handle_written(&mut self, w: Written) {
        let Some(waiting) = self.changes.waiting.remove(&w.id) else {
            return;
        };
        match waiting {
            Waiting::Refusal(c, reply) => {
                if w.result.is_err() {
                    lock(&self.shared.core).registry.note_audit_unwritten();
                }
                self.respond(c, reply).await;
            }
            Waiting::Tried(c, t) => {
                let dev = c.dev.clone();
                if self.finish_tried(c, &t, w.result).await {
                    if let Some(next) = self.changes.serial.done(&dev) {
                        self.run_changes(next).await;
                    }
                }
            }
            Waiting::Withdrawn(c, reply) => {
                let dev = c.dev.clone();
                self.respond(c, reply).await;
                if let Some(next) = self.changes.serial.done(&dev) {
                    self.run_changes(next).await;
                }
            }
        }
    }

    /// A tried change whose record is durable (or could not be written): made and replied
    /// to, refused, or withdrawn. Whether its device is done with it (a withdrawal waits for
    /// its own record).
    pub(super) async fn finish_tried(
        &mut self,
        c: Change,
        t: &Tried,
        written: Result<(), NotWritten>,
    ) -> bool {
        let dev = c.dev.clone();
        if let Err(e) = written {
            let reply = {
                let mut core = lock(&self.shared.core);
                let why = if e.in_doubt {
                    format!("in doubt: the audit file failed ({}); the change is not in force, but its record may be on the disk, so a restart of this service may put it in force: read the configuration after a restart", e.why)
                } else {
                    format!(
                        "the audit file could not be written ({}); nothing changed",
                        e.why
                    )
                };
                let reply = core.registry.refuse_request(&dev, why);
                let mut entry = t.entry.clone();
                (entry.accepted, entry.reason) = (false, reply.reason.clone());
                entry.changes.clear();
                core.registry.audit(entry);
                core.registry.note_audit_unwritten();
                reply
            };
            self.respond(c, reply).await;
            return true;
        }
        let made = lock(&self.shared.core).commit(&c, t);
        match made {
            Ok(reply) => {
                self.acknowledge(c, reply).await;
                true
            }
            Err(why) => self.withdraw(c, t, why).await,
        }
    }

    /// A change whose record says accepted could not be made: a record saying it was
    /// withdrawn, with the state in force, follows it; the reply waits for that record.
    pub(super) async fn withdraw(&mut self, c: Change, t: &Tried, why: String) -> bool {
        tracing::warn!(device = %printable(&c.dev), "change withdrawn after its record: {why}");
        let (reply, entry, now) = {
            let mut core = lock(&self.shared.core);
            let why = format!("withdrawn: {why}; nothing changed, send it again");
            let reply = core.registry.refuse_request(&c.dev, why);
            let mut entry = t.entry.clone();
            entry.n = core.gate.last_n_next();
            entry.unix_ns = protocol::unix_ns();
            (entry.accepted, entry.reason) = (false, reply.reason.clone());
            entry.changes.clear();
            core.registry.audit(entry.clone());
            (reply, entry, core.registry.state_of(&c.dev))
        };
        let trail = lock(&self.shared.core).gate.trail.clone();
        let (Some(trail), Some(now)) = (trail, now) else {
            self.respond(c, reply).await;
            return true;
        };
        let state = self.state_to_keep(&c.dev, &now);
        let w = Write::Record(Record {
            entry,
            state: Some(state),
        });
        let id = self.changes.next;
        self.changes.next += 1;
        self.changes
            .waiting
            .insert(id, Waiting::Withdrawn(c, reply));
        let sent = trail
            .send((w, Some((id, self.changes.written.clone()))))
            .await;
        if let Err(e) = sent {
            tracing::error!("{e}");
        }
        false
    }

    /// Reply to a change made: it is durable here if this member has an audit file, and
    /// acknowledged once the partners the fleet requires hold it ([`super::hold`]).
    pub(super) async fn acknowledge(&mut self, c: Change, mut reply: pb::ConfigReply) {
        reply.durable = lock(&self.shared.core).gate.trail.is_some();
        let Some(q) = c.query else { return };
        let hold = self.to_hold(&c.dev);
        self.reply_held(q, c.bytes, reply, hold).await;
    }

    /// Reply to a change not made (refused, withdrawn); a put has nobody to reply to, and
    /// its refusal is logged.
    pub(super) async fn respond(&mut self, c: Change, reply: pb::ConfigReply) {
        if !reply.accepted {
            self.refused(&c.dev, c.request.what(), &reply.reason);
        }
        let Some(q) = c.query else { return };
        let key = q.key_expr().as_str().to_string();
        let bytes = self.sealed_reply(&key, Some(&c.bytes), encode(&reply));
        let _ = q.reply(q.key_expr().clone(), bytes).await;
    }
}

//! Hot standby: two or more services of one group serve the same devices, one answers
//! (the active one, which sends heartbeats), the others step every sample without
//! answering, so their state is warm when they take over after the active one's silence.
//!
//! The rules only: no I/O, no clock. The service passes the time of each event in, so
//! the tests drive a takeover, a step-down and a split with plain instants.
//!
//! Terms order the members' claims: a member that takes over does so with one above the
//! highest term it holds or has heard, and when two members are active (both heard
//! nothing from each other), the higher term stays, and on equal terms the greater id.

use std::time::{Duration, Instant};

use protocol::pb;

use crate::config::{StandbyRole, StandbySpec};

/// How long a member that starts as `standby` waits, on top of the takeover time, before
/// it may take over: an active member starting at the same moment speaks first.
pub const STANDBY_GRACE: Duration = Duration::from_secs(1);

/// One member's hot-standby state.
#[derive(Debug, Clone)]
pub struct HotStandby {
    /// Whether this member answers (publishes commands and heartbeats). A standby still
    /// steps every sample.
    pub active: bool,
    /// Its term, sent in heartbeats and the status.
    pub term: u64,
    /// Heartbeat period, also the period of the takeover check. 10 ms without a group,
    /// where nothing uses it.
    pub heartbeat: Duration,
    /// Silence after which a standby takes over; never (`Duration::MAX`) without a group.
    takeover: Duration,
    /// When another member was last heard; at start, the start (an `active` member) or
    /// the start plus [`STANDBY_GRACE`] (a `standby` one).
    last_heard: Instant,
    /// Highest term heard from another member, so that a takeover outranks it.
    peer_term: u64,
}

impl HotStandby {
    /// A member started at `now`. Without a group the service is simply active; with one
    /// it starts silent and takes over after the takeover time (an `active` member at once
    /// if nobody speaks, a `standby` member after [`STANDBY_GRACE`] more).
    pub fn new(spec: Option<&StandbySpec>, now: Instant) -> Self {
        match spec {
            None => Self {
                active: true,
                term: 0,
                heartbeat: Duration::from_millis(10),
                takeover: Duration::MAX,
                last_heard: now,
                peer_term: 0,
            },
            Some(sb) => Self {
                active: false,
                term: 0,
                heartbeat: Duration::from_millis(sb.heartbeat_ms),
                takeover: Duration::from_millis(sb.takeover_ms),
                last_heard: match sb.role {
                    StandbyRole::Active => now,
                    StandbyRole::Standby => now + STANDBY_GRACE,
                },
                peer_term: 0,
            },
        }
    }

    /// A heartbeat period passed at `now`; true if this member just took over.
    pub fn on_tick(&mut self, now: Instant) -> bool {
        let silent = now.saturating_duration_since(self.last_heard);
        if !self.active && now > self.last_heard && silent > self.takeover {
            self.active = true;
            self.term = self.peer_term.max(self.term) + 1;
            return true;
        }
        false
    }

    /// A heartbeat of the group heard at `now` (this member's own are ignored); true if
    /// this member just stepped down.
    pub fn on_heartbeat(&mut self, me: &str, hb: &pb::Heartbeat, now: Instant) -> bool {
        if hb.controller_id == me {
            return false;
        }
        self.last_heard = self.last_heard.max(now);
        self.peer_term = self.peer_term.max(hb.term);
        let they_win =
            hb.term > self.term || (hb.term == self.term && hb.controller_id.as_str() > me);
        if self.active && they_win {
            self.active = false;
            return true;
        }
        false
    }

    /// The heartbeat this member sends while active.
    pub fn heartbeat_of(&self, me: &str) -> pb::Heartbeat {
        pb::Heartbeat {
            version: protocol::PROTOCOL_VERSION,
            controller_id: me.to_string(),
            term: self.term,
        }
    }
}

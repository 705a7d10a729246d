//! What a sample must be, whatever its device's state (rule 2's checks that need no
//! state, the limits of rules 3 and 4), and how it reached the registry.

use std::collections::VecDeque;

use protocol::{pb, printable};

/// Largest forward jump of `seq` within a run. An hour's outage at 100 Hz skips 360 000;
/// anything larger is garbage or hostile, and accepting it would make every later sample
/// of the real plant look stale.
pub const MAX_SEQ_JUMP: u64 = 1_000_000;
/// How far back (samples) a sequence may go and still be a late sample of the same run,
/// for plants that send no `run_id`; further back is taken for a restart.
pub const REORDER_WINDOW: u64 = 64;
/// Longest reason stored or sent back (bytes): reasons quote values from the network.
const MAX_REASON: usize = 240;
/// Consecutive samples of the run in force that the device refused as out of step (older
/// than the last answered one, past a sequence jump, or with a plant time that does not
/// advance) while forming a consistent stream of their own (sequence and time increasing)
/// before the device follows that stream as a new run. Whatever put the device ahead of
/// the plant (a jump of `seq` inside [`MAX_SEQ_JUMP`], a glitch of the plant's clock, a
/// forged sample), the real plant is locked out for at most this many samples.
pub const RESYNC_AFTER: u32 = 64;

/// A reason cut to [`MAX_REASON`] bytes (on a character boundary), so that no input can
/// make what the service stores, sends or logs large.
pub(super) fn capped(mut reason: String) -> String {
    if reason.len() > MAX_REASON {
        let mut end = MAX_REASON;
        while !reason.is_char_boundary(end) {
            end -= 1;
        }
        reason.truncate(end);
        reason.push_str("...");
    }
    reason
}

/// How a sample reached the registry: the device id of the key it came on (the key
/// decides the device), and the shard of the path it came by, which is where the
/// device's state is handed over from in a fleet: its own key's shard, or its gateway's
/// for a sample in a gateway's batch.
#[derive(Debug, Clone, Copy)]
pub struct Via<'a> {
    /// The device id from the key.
    pub key_id: &'a str,
    /// The shard of the path.
    pub home: u32,
    /// Whether this member is the one the fleet (or the hot standby) wants to command the
    /// path's shard: it claims a vacant lease at once ([`crate::lease`]).
    pub preferred: bool,
}

impl<'a> Via<'a> {
    /// A sample on the device's own key, to a preferred member.
    pub fn key(key_id: &'a str) -> Self {
        Self {
            key_id,
            home: protocol::shard_of(key_id),
            preferred: true,
        }
    }

    /// A sample in the batch of a gateway whose shard is `home`, to a preferred member.
    pub fn gateway(key_id: &'a str, home: u32) -> Self {
        Self {
            key_id,
            home,
            preferred: true,
        }
    }

    /// The same path, to a member that is preferred or not.
    pub fn preferred(self, preferred: bool) -> Self {
        Self { preferred, ..self }
    }
}

/// Median, 99th percentile and maximum of round trips (µs), nearest rank on the sorted
/// window; all zero (count 0) for an empty window.
pub fn latency(rtts: &VecDeque<u32>) -> pb::LatencyStats {
    if rtts.is_empty() {
        return pb::LatencyStats::default();
    }
    let mut v: Vec<u32> = rtts.iter().copied().collect();
    v.sort_unstable();
    let pick = |q: f64| f64::from(v[((v.len() - 1) as f64 * q).round() as usize]);
    pb::LatencyStats {
        count: v.len() as u32,
        p50_us: pick(0.5),
        p99_us: pick(0.99),
        max_us: f64::from(*v.last().unwrap_or(&0)),
    }
}

/// The checks of rule 2 that need no state: the sample's `device_id` is the key's, and
/// every value is finite. The service runs them in Zenoh's callback, before a sample may
/// take its device's place in the inbox (so garbage cannot supersede a real sample), and
/// [`Registry::handle_sample`] runs them again. The reason is cut to printable length.
pub fn precheck(key_id: &str, s: &pb::Sample) -> Result<(), String> {
    if s.device_id != key_id {
        return Err(format!(
            "device id \"{}\" in a sample on the key of \"{key_id}\"",
            printable(&s.device_id)
        ));
    }
    if let Some(bad) = s.outputs.iter().chain(&s.applied).find(|v| !v.is_finite()) {
        return Err(format!("non-finite value {bad:?}"));
    }
    if !s.plant_time.is_finite() {
        return Err(format!("non-finite plant time {:?}", s.plant_time));
    }
    Ok(())
}

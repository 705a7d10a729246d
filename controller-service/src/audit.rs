//! The audit trail's rules, without I/O: what an entry says (IEC 62443-4-2 CR 2.8: when,
//! where, who, what, with what result), how a change's old and new values are found, how
//! the entries a partner hands over join a device's own, and the file's line format. The
//! file itself (append-only, fsynced, rotated) is written by `service::audit`.
//!
//! Every decision on an operator's change is an entry, accepted or refused: a change of
//! laws, gains, maps or reference, an envelope change. Reads are not. A device keeps its
//! latest [`KEPT`] entries in memory and hands them over with its state, so the member
//! that takes a device over (a standby holding a change, a takeover, a shard handover)
//! answers `mfcctl audit` with the history of the member before it.

use std::collections::{BTreeMap, VecDeque};

use protocol::pb;

/// Entries a device keeps and hands over (the file keeps every one).
pub const KEPT: usize = 64;

/// Of those, refusals kept at most: an operator who floods refused requests (a viewer
/// trying changes, say) pushes out older refusals, never the changes that were made.
pub const REFUSALS_KEPT: usize = KEPT / 2;

/// Longest `asked` kept (characters): a refused request is recorded abridged.
const ASKED_LEN: usize = 400;

/// The settings that changed between two views of a device ([`crate::Registry::settings_of`]),
/// in the views' order; a setting present on one side only shows `""` on the other.
pub fn diff(
    before: &BTreeMap<String, String>,
    after: &BTreeMap<String, String>,
) -> Vec<pb::AuditChange> {
    let mut keys: Vec<&String> = before.keys().chain(after.keys()).collect();
    keys.sort();
    keys.dedup();
    keys.into_iter()
        .filter_map(|k| {
            let (old, new) = (before.get(k), after.get(k));
            (old != new).then(|| pb::AuditChange {
                what: k.clone(),
                old: old.cloned().unwrap_or_default(),
                new: new.cloned().unwrap_or_default(),
            })
        })
        .collect()
}

/// A refused request as the entry records it: at most [`ASKED_LEN`] characters (then
/// `…`), control characters escaped.
pub fn abridged(asked: &str) -> String {
    let mut out = String::new();
    for (i, c) in asked.chars().enumerate() {
        if i == ASKED_LEN {
            out.push('…');
            break;
        }
        if c.is_control() {
            out.extend(c.escape_debug());
        } else {
            out.push(c);
        }
    }
    out
}

/// Add `entry` to a device's latest entries, dropping the oldest beyond [`KEPT`] (and the
/// oldest refusals beyond [`REFUSALS_KEPT`]).
pub fn push(tail: &mut VecDeque<pb::AuditEntry>, entry: pb::AuditEntry) {
    tail.push_back(entry);
    trim(tail);
}

/// Keep the newest entries: at most [`KEPT`], of which at most [`REFUSALS_KEPT`] refused.
fn trim(tail: &mut VecDeque<pb::AuditEntry>) {
    let refused = tail.iter().filter(|e| !e.accepted).count();
    if tail.len() <= KEPT && refused <= REFUSALS_KEPT {
        return;
    }
    let (mut kept, mut refusals) = (VecDeque::with_capacity(KEPT), 0);
    while let Some(e) = tail.pop_back() {
        if kept.len() == KEPT {
            break;
        }
        if !e.accepted {
            if refusals == REFUSALS_KEPT {
                continue;
            }
            refusals += 1;
        }
        kept.push_front(e);
    }
    *tail = kept;
}

/// Join the entries a partner handed over to a device's own: those not already there
/// (by member and number) are added, the whole kept in time order and at most [`KEPT`].
/// Returns the ones added, for this member's file. At most [`KEPT`] are looked at: a
/// hostile state cannot make the tail grow.
pub fn merge(
    tail: &mut VecDeque<pb::AuditEntry>,
    handed: &[pb::AuditEntry],
) -> Vec<pb::AuditEntry> {
    let new: Vec<pb::AuditEntry> = handed
        .iter()
        .rev()
        .take(KEPT)
        .filter(|e| !tail.iter().any(|t| t.member == e.member && t.n == e.n))
        .cloned()
        .collect();
    if new.is_empty() {
        return new;
    }
    let mut all: Vec<pb::AuditEntry> = tail.drain(..).chain(new.iter().cloned()).collect();
    all.sort_by(|a, b| (a.unix_ns, &a.member, a.n).cmp(&(b.unix_ns, &b.member, b.n)));
    tail.extend(all);
    trim(tail);
    let mut new = new;
    new.reverse();
    new
}

/// The next entry number of a member: after `last`, and at least the time (ns), so that
/// numbers never repeat across the member's restarts (given a clock that does not go back
/// by more than the restart takes).
pub fn next_number(last: u64, unix_ns: u64) -> u64 {
    unix_ns.max(last + 1)
}

/// One line of the audit file (JSON, without its newline), as an older build wrote it: an
/// entry alone, without the state and CRC that `crate::journal::to_line` adds.
pub fn to_line(e: &pb::AuditEntry) -> String {
    entry_json(e).to_string()
}

/// An entry's fields as the audit file's JSON object.
pub fn entry_json(e: &pb::AuditEntry) -> serde_json::Value {
    let changes: Vec<serde_json::Value> = e
        .changes
        .iter()
        .map(|c| serde_json::json!({ "what": c.what, "old": c.old, "new": c.new }))
        .collect();
    serde_json::json!({
        "unix_ns": e.unix_ns,
        "member": e.member,
        "n": e.n,
        "device": e.device_id,
        "operator": e.operator,
        "verified": e.verified,
        "role": e.role,
        "action": e.action,
        "changes": changes,
        "asked": e.asked,
        "accepted": e.accepted,
        "reason": e.reason,
    })
}

/// An entry from one line of the audit file (`None` if the line is not one). Fields it
/// does not know (a journal line's `state` and `crc`) are ignored.
pub fn from_line(line: &str) -> Option<pb::AuditEntry> {
    entry_from_json(&serde_json::from_str(line).ok()?)
}

/// An entry from the audit file's JSON object (`None` if it is not one).
pub fn entry_from_json(v: &serde_json::Value) -> Option<pb::AuditEntry> {
    let s = |k: &str| v.get(k).and_then(|x| x.as_str()).map(str::to_string);
    let changes = v
        .get("changes")?
        .as_array()?
        .iter()
        .map(|c| {
            let f = |k: &str| c.get(k).and_then(|x| x.as_str()).map(str::to_string);
            Some(pb::AuditChange {
                what: f("what")?,
                old: f("old")?,
                new: f("new")?,
            })
        })
        .collect::<Option<Vec<_>>>()?;
    Some(pb::AuditEntry {
        unix_ns: v.get("unix_ns")?.as_u64()?,
        member: s("member")?,
        n: v.get("n")?.as_u64()?,
        device_id: s("device")?,
        operator: s("operator")?,
        verified: v.get("verified")?.as_bool()?,
        role: s("role")?,
        action: s("action")?,
        changes,
        asked: s("asked")?,
        accepted: v.get("accepted")?.as_bool()?,
        reason: s("reason")?,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn entry(member: &str, n: u64) -> pb::AuditEntry {
        pb::AuditEntry {
            unix_ns: n,
            member: member.into(),
            n,
            device_id: "aero-1".into(),
            operator: "alice".into(),
            verified: true,
            role: "operator".into(),
            action: "configuration".into(),
            changes: vec![pb::AuditChange {
                what: "channel 0 kp".into(),
                old: "2".into(),
                new: "3\"\n".into(),
            }],
            asked: String::new(),
            accepted: true,
            reason: String::new(),
        }
    }

    #[test]
    fn a_diff_names_what_moved_only() {
        let m = |kv: &[(&str, &str)]| -> BTreeMap<String, String> {
            kv.iter()
                .map(|(k, v)| (k.to_string(), v.to_string()))
                .collect()
        };
        let d = diff(
            &m(&[("a", "1"), ("b", "2"), ("gone", "x")]),
            &m(&[("a", "1"), ("b", "5"), ("new", "y")]),
        );
        let got: Vec<_> = d.iter().map(|c| (&*c.what, &*c.old, &*c.new)).collect();
        assert_eq!(got, [("b", "2", "5"), ("gone", "x", ""), ("new", "", "y")]);
    }

    #[test]
    fn handed_entries_join_once_in_time_order_and_bounded() {
        let mut tail: VecDeque<_> = [entry("c-1", 10), entry("c-1", 30)].into();
        let added = merge(
            &mut tail,
            &[entry("c-1", 10), entry("c-2", 20), entry("c-1", 30)],
        );
        assert_eq!(added.len(), 1);
        assert_eq!(added[0].member, "c-2");
        let order: Vec<u64> = tail.iter().map(|e| e.n).collect();
        assert_eq!(order, [10, 20, 30]);
        assert!(merge(&mut tail, &[entry("c-2", 20)]).is_empty());
        let flood: Vec<_> = (100..1000).map(|n| entry("x", n)).collect();
        let added = merge(&mut tail, &flood);
        assert_eq!(added.len(), KEPT);
        assert_eq!(tail.len(), KEPT);
        assert_eq!(tail.back().unwrap().n, 999);
    }

    #[test]
    fn a_flood_of_refusals_never_pushes_out_the_changes_made() {
        let mut tail = VecDeque::new();
        for n in 0..10 {
            push(&mut tail, entry("c-1", n));
        }
        let refusal = |n| pb::AuditEntry {
            accepted: false,
            ..entry("c-1", n)
        };
        for n in 10..1000 {
            push(&mut tail, refusal(n));
        }
        assert_eq!(tail.len(), 10 + REFUSALS_KEPT);
        let made: Vec<u64> = tail.iter().filter(|e| e.accepted).map(|e| e.n).collect();
        assert_eq!(made, (0..10).collect::<Vec<_>>());
        assert_eq!(tail.back().unwrap().n, 999, "the newest refusals stay");
        // Changes made later still push out the oldest of all.
        for n in 1000..1100 {
            push(&mut tail, entry("c-1", n));
        }
        assert_eq!(tail.len(), KEPT);
        assert!(tail.iter().all(|e| e.accepted && e.n >= 1036));
        // A partner's flood of refusals handed over is held to the same bound.
        let flood: Vec<_> = (2000..2100).map(refusal).collect();
        merge(&mut tail, &flood);
        assert_eq!(tail.iter().filter(|e| !e.accepted).count(), REFUSALS_KEPT);
        assert_eq!(tail.len(), KEPT);
    }

    #[test]
    fn lines_read_back_and_garbage_is_no_entry() {
        let e = entry("c-1", 7);
        assert_eq!(from_line(&to_line(&e)), Some(e));
        for bad in ["", "{}", "not json", r#"{"unix_ns": -1}"#] {
            assert_eq!(from_line(bad), None, "{bad}");
        }
        assert_eq!(next_number(5, 3), 6);
        assert_eq!(next_number(5, 100), 100);
        let long = "x".repeat(1000);
        assert_eq!(abridged(&long).chars().count(), ASKED_LEN + 1);
        assert_eq!(abridged("a\u{7}b"), "a\\u{7}b");
    }
}

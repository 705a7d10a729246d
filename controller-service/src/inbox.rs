//! Where samples wait between Zenoh's callbacks and the worker that serves them.
//!
//! A control loop wants the newest sample of each device, not every sample: a command for
//! an old sample is applied late or not at all. So the inbox keeps at most one unread
//! sample per device. A newer one replaces it (counted as superseded), and devices are
//! served in the order their pending sample arrived. What waits is therefore bounded by
//! the number of devices, never by one device's rate: a device flooding samples delays
//! every other device by at most one sample of its own.
//!
//! Only well-formed samples get this far (decoded, of the key's own device, finite values:
//! the callbacks check that first), so garbage on a device's key cannot push that
//! device's real samples out, and neither can a replay of its old samples (an older
//! sample of the same run never replaces a newer one). What remains is a well-formed
//! sample of a new run or a later sequence, which only the device's own identity can send
//! once access control is on (`deploy/`): within one device, the latest sample wins.
//!
//! Devices the service does not serve (yet: the first sample of a template device comes
//! this way) share a small fixed number of slots, so a flood of unknown keys fills those
//! and is dropped (counted as queue full) without touching the slots of served devices.
//!
//! A gateway's batches wait here too, one entry per gateway, but there a newer batch does
//! not always hold a newer sample of every plant: a gateway sends a period in parts when a
//! plant is late. So a gateway's entry is its unread [`Parts`], up to one period's worth
//! of samples: a part joins them, a complete batch replaces them.
//!
//! Pure data: the service wraps it in a mutex that is held only to push or pop.

use std::collections::{HashMap, HashSet, VecDeque};

/// What became of a pushed sample.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Push {
    /// The device had nothing pending: the sample waits, and the worker must be woken.
    Queued,
    /// It replaced the device's unread sample (the worker is already due to come).
    Superseded,
    /// It joined the device's unread item, replacing nothing (the worker is due).
    Joined,
    /// No slot left for a device the service does not serve: dropped.
    Full,
}

#[derive(Debug)]
struct Pending<T> {
    item: T,
    /// Samples of this device this one replaced.
    superseded: u64,
}

/// The latest unread sample (`T`) of each device, in arrival order.
#[derive(Debug)]
pub struct Inbox<T> {
    pending: HashMap<String, Pending<T>>,
    ready: VecDeque<String>,
    served: HashSet<String>,
    /// Pending samples of devices not in `served`.
    others: usize,
    others_cap: usize,
    superseded: u64,
    full: u64,
}

/// A sample taken out of the inbox.
#[derive(Debug, PartialEq, Eq)]
pub struct Taken<T> {
    /// The device id from the key.
    pub id: String,
    /// The sample.
    pub item: T,
    /// How many older samples of the device it replaced while waiting.
    pub superseded: u64,
}

impl<T> Inbox<T> {
    /// An empty inbox whose unserved devices share `others_cap` slots (at least 1).
    pub fn new(others_cap: usize) -> Self {
        Self {
            pending: HashMap::new(),
            ready: VecDeque::new(),
            served: HashSet::new(),
            others: 0,
            others_cap: others_cap.max(1),
            superseded: 0,
            full: 0,
        }
    }

    /// Give device `id` a slot of its own: the worker calls this once it serves `id`.
    pub fn serve(&mut self, id: &str) {
        if self.served.insert(id.to_string()) && self.pending.contains_key(id) {
            // Its pending sample no longer takes one of the shared slots.
            self.others -= 1;
        }
    }

    /// Take device `id`'s own slot away (it is no longer served here); a sample of it
    /// still pending is dropped.
    pub fn unserve(&mut self, id: &str) {
        if self.served.remove(id) && self.pending.remove(id).is_some() {
            self.ready.retain(|r| r != id);
        }
    }

    /// Whether device `id` has a slot of its own (it is served).
    pub fn serves(&self, id: &str) -> bool {
        self.served.contains(id)
    }

    /// Put a sample of device `id` in.
    pub fn push(&mut self, id: &str, item: T) -> Push {
        self.push_unless_older(id, item, |_, _| false)
    }

    /// Put a sample of device `id` in, unless `older(new, pending)` says it is older than
    /// the one already waiting: then the waiting one stays and the new one is dropped,
    /// counted as superseded all the same (a newer sample of its device is served
    /// instead). A replay of old samples thus cannot push a device's newest one out.
    pub fn push_unless_older(&mut self, id: &str, item: T, older: impl Fn(&T, &T) -> bool) -> Push {
        self.push_merged(id, item, |pending, new| {
            if !older(&new, pending) {
                *pending = new;
            }
            1
        })
    }

    /// Put an item of `id` in; if one is already pending, `merge(pending, new)` makes one
    /// of the two and says how many items it dropped as superseded (counted).
    pub fn push_merged(&mut self, id: &str, item: T, merge: impl FnOnce(&mut T, T) -> u64) -> Push {
        if let Some(p) = self.pending.get_mut(id) {
            let dropped = merge(&mut p.item, item);
            p.superseded += dropped;
            self.superseded += dropped;
            return if dropped > 0 {
                Push::Superseded
            } else {
                Push::Joined
            };
        }
        if !self.served.contains(id) {
            if self.others >= self.others_cap {
                self.full += 1;
                return Push::Full;
            }
            self.others += 1;
        }
        self.pending.insert(
            id.to_string(),
            Pending {
                item,
                superseded: 0,
            },
        );
        self.ready.push_back(id.to_string());
        Push::Queued
    }

    /// Take the sample of the device that has waited longest.
    pub fn pop(&mut self) -> Option<Taken<T>> {
        let id = self.ready.pop_front()?;
        let p = self.pending.remove(&id)?;
        if !self.served.contains(&id) {
            self.others -= 1;
        }
        Some(Taken {
            id,
            item: p.item,
            superseded: p.superseded,
        })
    }

    /// Samples waiting (one per device at most).
    pub fn len(&self) -> usize {
        self.ready.len()
    }

    /// Whether nothing waits.
    pub fn is_empty(&self) -> bool {
        self.ready.is_empty()
    }

    /// Items replaced by a newer one of the same device, since the start.
    pub fn superseded(&self) -> u64 {
        self.superseded
    }

    /// Samples dropped for lack of a slot, since the start.
    pub fn full(&self) -> u64 {
        self.full
    }
}

/// Most unread batches a gateway keeps side by side: a period split in two or three by
/// late plants, and a little room. Bounded, so a gateway sending many small parts costs
/// a fixed amount.
pub const PARTS: usize = 4;

/// What a gateway's unread batches may hold in all: beyond it, the oldest go.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Cap {
    /// Samples: the plants the gateway hosts. A gateway's period holds one sample of each,
    /// so more than that holds an older sample of some plant than a newer batch does.
    pub samples: usize,
    /// Encoded bytes: one batch's bound, so that a gateway's entry costs no more memory
    /// than one batch did.
    pub bytes: usize,
}

#[derive(Debug, Clone, PartialEq, Eq)]
struct Part<T> {
    item: T,
    samples: usize,
    bytes: usize,
}

/// A gateway's unread batches, oldest first.
///
/// A gateway sends a period in parts when plants are late, so a newer batch does not
/// always hold a newer sample of every plant than the unread ones. The parts are kept
/// side by side, within a [`Cap`] of one period's samples (and [`PARTS`] batches, and one
/// batch's bytes): a complete batch (one sample of each plant) leaves room for nothing
/// older, and a worker a period behind serves one period's worth, not every part it
/// missed. What the oldest parts held beyond the cap is what the worker would have served
/// late, if at all.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Parts<T>(Vec<Part<T>>);

impl<T> Parts<T> {
    /// One batch of `samples` samples, `bytes` long.
    pub fn one(item: T, samples: usize, bytes: usize) -> Self {
        Self(vec![Part {
            item,
            samples,
            bytes,
        }])
    }

    /// Take in the gateway's newer batches (one, as pushed: [`Parts::one`]), then let the
    /// oldest go while more than `cap` or [`PARTS`] batches wait (the newest always
    /// stays). Returns how many went.
    pub fn join(&mut self, newer: Self, cap: Cap) -> u64 {
        self.0.extend(newer.0);
        let mut samples: usize = self.0.iter().map(|p| p.samples).sum();
        let mut bytes: usize = self.0.iter().map(|p| p.bytes).sum();
        let mut gone = 0;
        while self.0.len() > gone + 1
            && (self.0.len() - gone > PARTS || samples > cap.samples || bytes > cap.bytes)
        {
            samples -= self.0[gone].samples;
            bytes -= self.0[gone].bytes;
            gone += 1;
        }
        self.0.drain(..gone);
        gone as u64
    }

    /// The batches, oldest first.
    pub fn into_vec(self) -> Vec<T> {
        self.0.into_iter().map(|p| p.item).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_flooding_device_supersedes_itself_and_delays_no_one() {
        let mut inbox: Inbox<Vec<u8>> = Inbox::new(4);
        inbox.serve("good");
        inbox.serve("flood");
        assert_eq!(inbox.push("flood", vec![0]), Push::Queued);
        assert_eq!(inbox.push("good", vec![1]), Push::Queued);
        for k in 2..10_000u32 {
            assert_eq!(
                inbox.push("flood", k.to_le_bytes().to_vec()),
                Push::Superseded
            );
        }
        assert_eq!(inbox.len(), 2);
        let first = inbox.pop().unwrap();
        assert_eq!(first.id, "flood");
        assert_eq!(first.item, 9_999u32.to_le_bytes().to_vec(), "latest wins");
        assert_eq!(first.superseded, 9_998);
        assert_eq!(inbox.pop().unwrap().id, "good");
        assert!(inbox.pop().is_none());
        assert_eq!(inbox.superseded(), 9_998);
    }

    #[test]
    fn unknown_keys_share_a_few_slots_and_never_take_a_served_devices() {
        let mut inbox: Inbox<Vec<u8>> = Inbox::new(3);
        inbox.serve("good");
        for k in 0..1000 {
            inbox.push(&format!("x{k}"), vec![]);
        }
        assert_eq!(inbox.len(), 3);
        assert_eq!(inbox.full(), 997);
        assert_eq!(inbox.push("good", vec![7]), Push::Queued);
        assert_eq!(inbox.len(), 4);
        // Served in arrival order; popping frees the shared slots.
        let ids: Vec<String> = std::iter::from_fn(|| inbox.pop().map(|t| t.id)).collect();
        assert_eq!(ids, ["x0", "x1", "x2", "good"]);
        assert_eq!(inbox.push("x5", vec![]), Push::Queued);
    }

    #[test]
    fn a_device_served_while_pending_frees_its_shared_slot() {
        let mut inbox: Inbox<Vec<u8>> = Inbox::new(1);
        assert_eq!(inbox.push("new", vec![]), Push::Queued);
        assert_eq!(inbox.push("other", vec![]), Push::Full);
        inbox.serve("new");
        assert_eq!(inbox.push("other", vec![]), Push::Queued);
        assert_eq!(inbox.pop().unwrap().id, "new");
        assert_eq!(inbox.pop().unwrap().id, "other");
        assert!(inbox.is_empty());
        assert_eq!(inbox.push("third", vec![]), Push::Queued);
    }

    #[test]
    fn a_period_in_parts_loses_no_part_and_a_newer_period_replaces_it() {
        let mut inbox: Inbox<Parts<&str>> = Inbox::new(4);
        inbox.serve("gw");
        // A gateway of four plants.
        let cap = Cap {
            samples: 4,
            bytes: 1000,
        };
        let push = |inbox: &mut Inbox<Parts<&str>>, name, samples| {
            inbox.push_merged("gw", Parts::one(name, samples, 10), |p, new| {
                p.join(new, cap)
            })
        };
        // Three plants on time, then the late one's sample alone: both kept, in order.
        assert_eq!(push(&mut inbox, "abc", 3), Push::Queued);
        assert_eq!(push(&mut inbox, "d", 1), Push::Joined);
        let t = inbox.pop().unwrap();
        assert_eq!((t.item.into_vec(), t.superseded), (vec!["abc", "d"], 0));
        // One plant silent: each period is a part of three. The worker a period behind
        // finds the newer period's, not both.
        push(&mut inbox, "abc-1", 3);
        assert_eq!(push(&mut inbox, "abc-2", 3), Push::Superseded);
        assert_eq!(inbox.pop().unwrap().item.into_vec(), ["abc-2"]);
        // A late plant's part, then the next period's parts: the late sample stays as long
        // as the period's samples fit.
        push(&mut inbox, "d-1", 1);
        assert_eq!(push(&mut inbox, "abc-2", 3), Push::Joined);
        assert_eq!(push(&mut inbox, "d-2", 1), Push::Superseded);
        assert_eq!(inbox.pop().unwrap().item.into_vec(), ["abc-2", "d-2"]);
        // A complete batch leaves room for nothing older.
        push(&mut inbox, "a", 1);
        push(&mut inbox, "b", 1);
        assert_eq!(push(&mut inbox, "abcd", 4), Push::Superseded);
        let t = inbox.pop().unwrap();
        assert_eq!((t.item.into_vec(), t.superseded), (vec!["abcd"], 2));
        assert_eq!(inbox.superseded(), 4);
    }

    #[test]
    fn parts_are_bounded_in_count_and_bytes_and_the_newest_always_stays() {
        let wide = Cap {
            samples: 100,
            bytes: 100,
        };
        let mut p = Parts::one(0, 1, 10);
        for k in 1..=PARTS {
            p.join(Parts::one(k, 1, 10), wide);
        }
        assert_eq!(p.clone().into_vec(), (1..=PARTS).collect::<Vec<_>>());
        // Bytes: a part of 95 leaves room for nothing older.
        assert_eq!(p.join(Parts::one(9, 1, 95), wide), PARTS as u64);
        assert_eq!(p.clone().into_vec(), [9]);
        // The newest stays even beyond the cap (a batch is bounded where it is taken in).
        assert_eq!(p.join(Parts::one(10, 500, 500), wide), 1);
        assert_eq!(p.into_vec(), [10]);
        // No plant count (a gateway older than the field): a newer batch replaces.
        let old = Cap {
            samples: 0,
            bytes: 100,
        };
        let mut p = Parts::one("x", 3, 10);
        assert_eq!(p.join(Parts::one("y", 1, 10), old), 1);
        assert_eq!(p.into_vec(), ["y"]);
    }

    #[test]
    fn an_older_sample_does_not_push_out_a_newer_one() {
        let mut inbox = Inbox::new(4);
        inbox.serve("a");
        let older = |new: &(u64, u64), old: &(u64, u64)| new.0 == old.0 && new.1 < old.1;
        assert_eq!(inbox.push_unless_older("a", (1, 10), older), Push::Queued);
        assert_eq!(
            inbox.push_unless_older("a", (1, 3), older),
            Push::Superseded
        );
        assert_eq!(inbox.pop().unwrap().item, (1, 10));
        inbox.push_unless_older("a", (1, 10), older);
        // Another run is not older: it replaces.
        inbox.push_unless_older("a", (2, 0), older);
        let t = inbox.pop().unwrap();
        assert_eq!((t.item, t.superseded), ((2, 0), 1));
    }
}

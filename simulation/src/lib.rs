//! What every seeded simulation of the project shares, so that they are written once:
//!
//! * [`SplitMix`]: one generator (SplitMix64). A seed replays exactly, on every machine, and a
//!   failing seed printed by a test is all it takes to run the same schedule again.
//! * [`Events`]: one queue of timed events, the earliest first and, at one instant, in
//!   the order they were queued, so that two simulations given the same inputs take the
//!   same steps.
//!
//! Time is whatever the caller counts in (`u64` nanoseconds, milliseconds, or a
//! [`std::time::Duration`]): anything ordered and copyable. Nothing here reads a clock or
//! does I/O; the simulations built on it drive the project's real, pure rules.

#![forbid(unsafe_code)]

use std::cmp::{Ordering, Reverse};
use std::collections::BinaryHeap;

/// SplitMix64 (Steele, Lea and Flood, 2014): 64 bits of state, every seed usable (0
/// included), and a full period of 2^64. Small and fast; not for anything secret.
#[derive(Debug, Clone)]
pub struct SplitMix(u64);

impl SplitMix {
    /// The generator of `seed`.
    pub fn new(seed: u64) -> Self {
        Self(seed)
    }

    /// The next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// A number in `0..n` (0 for `n` = 0). The remainder's bias, below 2^-40 for any `n`
    /// under 2^24, does not matter to a schedule of faults.
    pub fn below(&mut self, n: u64) -> u64 {
        self.next_u64() % n.max(1)
    }

    /// A number in `lo..=hi`.
    pub fn between(&mut self, lo: u64, hi: u64) -> u64 {
        lo + self.next_u64() % (hi - lo + 1)
    }

    /// Uniform in `[0, 1)`, from the top 53 bits.
    pub fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// `true` with probability `p` (never for `p` <= 0, always for `p` >= 1).
    pub fn chance(&mut self, p: f64) -> bool {
        self.uniform() > 1.0 - p
    }

    /// One of `xs`, each as likely. Panics on an empty slice.
    pub fn pick<T: Copy>(&mut self, xs: &[T]) -> T {
        xs[self.below(xs.len() as u64) as usize]
    }
}

/// A queue of events at times `T`: [`Events::pop`] gives the earliest, and of those at
/// one instant the first queued. The order never depends on the events themselves.
#[derive(Debug)]
pub struct Events<T: Ord + Copy, E> {
    heap: BinaryHeap<Reverse<Entry<T, E>>>,
    queued: u64,
}

#[derive(Debug)]
struct Entry<T, E> {
    at: T,
    n: u64,
    event: E,
}

impl<T: Ord, E> PartialEq for Entry<T, E> {
    fn eq(&self, other: &Self) -> bool {
        self.cmp(other) == Ordering::Equal
    }
}
impl<T: Ord, E> Eq for Entry<T, E> {}
impl<T: Ord, E> PartialOrd for Entry<T, E> {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}
impl<T: Ord, E> Ord for Entry<T, E> {
    fn cmp(&self, other: &Self) -> Ordering {
        (&self.at, self.n).cmp(&(&other.at, other.n))
    }
}

impl<T: Ord + Copy, E> Default for Events<T, E> {
    fn default() -> Self {
        Self {
            heap: BinaryHeap::new(),
            queued: 0,
        }
    }
}

impl<T: Ord + Copy, E> Events<T, E> {
    /// An empty queue.
    pub fn new() -> Self {
        Self::default()
    }

    /// Queue `event` at `at`.
    pub fn push(&mut self, at: T, event: E) {
        self.queued += 1;
        self.heap.push(Reverse(Entry {
            at,
            n: self.queued,
            event,
        }));
    }

    /// The time of the earliest event, if any.
    pub fn next_at(&self) -> Option<T> {
        self.heap.peek().map(|Reverse(e)| e.at)
    }

    /// The earliest event and its time.
    pub fn pop(&mut self) -> Option<(T, E)> {
        self.heap.pop().map(|Reverse(e)| (e.at, e.event))
    }

    /// The earliest event if it is due at or before `until`.
    pub fn pop_until(&mut self, until: T) -> Option<(T, E)> {
        if self.next_at()? > until {
            return None;
        }
        self.pop()
    }

    /// The earliest event if it is due strictly before `end`.
    pub fn pop_before(&mut self, end: T) -> Option<(T, E)> {
        if self.next_at()? >= end {
            return None;
        }
        self.pop()
    }

    /// Events waiting.
    pub fn len(&self) -> usize {
        self.heap.len()
    }

    /// Whether none waits.
    pub fn is_empty(&self) -> bool {
        self.heap.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn splitmix64_gives_its_published_sequence() {
        // The reference implementation's first outputs for seed 1234567.
        let mut r = SplitMix::new(1_234_567);
        let got: Vec<u64> = (0..3).map(|_| r.next_u64()).collect();
        assert_eq!(
            got,
            [
                6_457_827_717_110_365_317,
                3_203_168_211_198_807_973,
                9_817_491_932_198_370_423
            ]
        );
    }

    #[test]
    fn a_seed_replays_and_two_seeds_differ() {
        let a: Vec<u64> = {
            let mut r = SplitMix::new(7);
            (0..100).map(|_| r.next_u64()).collect()
        };
        let b: Vec<u64> = {
            let mut r = SplitMix::new(7);
            (0..100).map(|_| r.next_u64()).collect()
        };
        let c: Vec<u64> = {
            let mut r = SplitMix::new(8);
            (0..100).map(|_| r.next_u64()).collect()
        };
        assert_eq!(a, b);
        assert_ne!(a, c);
    }

    #[test]
    fn draws_stay_in_their_ranges_and_chance_follows_p() {
        let mut r = SplitMix::new(0);
        let mut hits = 0;
        for _ in 0..100_000 {
            assert!(r.below(7) < 7);
            assert!((3..=5).contains(&r.between(3, 5)));
            let u = r.uniform();
            assert!((0.0..1.0).contains(&u));
            hits += u32::from(r.chance(0.25));
        }
        assert!(
            (24_000..26_000).contains(&hits),
            "{hits} of 100000 at p = 0.25"
        );
        assert!(!r.chance(0.0));
        assert!(r.chance(1.0));
    }

    #[test]
    fn events_come_earliest_first_and_in_queued_order_at_one_instant() {
        let mut q = Events::new();
        q.push(5u64, "c");
        q.push(1, "a");
        q.push(5, "d");
        q.push(3, "b");
        q.push(5, "e");
        assert_eq!(q.len(), 5);
        assert_eq!(q.pop_before(1), None);
        assert_eq!(q.pop_until(1), Some((1, "a")));
        assert_eq!(q.pop_until(4), Some((3, "b")));
        assert_eq!(q.pop_until(4), None);
        let rest: Vec<_> = std::iter::from_fn(|| q.pop()).collect();
        assert_eq!(rest, [(5, "c"), (5, "d"), (5, "e")]);
        assert!(q.is_empty());
    }
}

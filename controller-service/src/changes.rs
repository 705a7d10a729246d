//! One change per device at a time, without I/O: a change is decided on the state in force,
//! and that state must not move until the change's record is durable and the change is in
//! force itself (`service::operators`). So while one change of a device is being written,
//! the next ones wait here, in the order they came, and each is decided only once the one
//! before it is done. Bounded: a device's queue and all of them together; what does not fit
//! is refused at once, so that a flood on one device never holds another's changes back.

use std::collections::{HashMap, VecDeque};

/// Changes that may wait behind the one being written, for one device.
pub const PER_DEVICE: usize = 32;

/// Changes that may wait, every device together.
pub const IN_ALL: usize = 1024;

/// What to do with a change that arrives.
#[derive(Debug, PartialEq, Eq)]
pub enum Arrival<T> {
    /// Decide it now: no change of its device is being written.
    Now(T),
    /// It waits behind the one being written.
    Queued,
    /// No room: refuse it (how many wait for its device).
    Full(T, usize),
}

/// The devices with a change being written, and the changes waiting behind each.
#[derive(Debug)]
pub struct Serial<T> {
    busy: HashMap<String, VecDeque<T>>,
    waiting: usize,
}

impl<T> Default for Serial<T> {
    fn default() -> Self {
        Self {
            busy: HashMap::new(),
            waiting: 0,
        }
    }
}

impl<T> Serial<T> {
    /// A change of `dev` arrives.
    pub fn arrive(&mut self, dev: &str, change: T) -> Arrival<T> {
        match self.busy.get_mut(dev) {
            None => {
                self.busy.insert(dev.to_string(), VecDeque::new());
                Arrival::Now(change)
            }
            Some(q) if q.len() >= PER_DEVICE || self.waiting >= IN_ALL => {
                Arrival::Full(change, q.len())
            }
            Some(q) => {
                q.push_back(change);
                self.waiting += 1;
                Arrival::Queued
            }
        }
    }

    /// The change of `dev` being decided or written is done (in force, refused or
    /// withdrawn): the next one to decide, if one waits; otherwise the device is free.
    pub fn done(&mut self, dev: &str) -> Option<T> {
        let q = self.busy.get_mut(dev)?;
        match q.pop_front() {
            Some(next) => {
                self.waiting -= 1;
                Some(next)
            }
            None => {
                self.busy.remove(dev);
                None
            }
        }
    }

    /// Whether a change of `dev` is being decided or written.
    pub fn busy(&self, dev: &str) -> bool {
        self.busy.contains_key(dev)
    }

    /// Changes waiting, every device together.
    pub fn waiting(&self) -> usize {
        self.waiting
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn changes_of_one_device_go_one_at_a_time_in_order_and_bounded() {
        let mut s = Serial::default();
        assert_eq!(s.arrive("a", 1), Arrival::Now(1));
        assert_eq!(
            s.arrive("b", 10),
            Arrival::Now(10),
            "another device is not held back"
        );
        for k in 2..2 + PER_DEVICE as u32 {
            assert_eq!(s.arrive("a", k), Arrival::Queued);
        }
        assert_eq!(s.arrive("a", 99), Arrival::Full(99, PER_DEVICE));
        assert_eq!(s.waiting(), PER_DEVICE);
        for k in 2..2 + PER_DEVICE as u32 {
            assert_eq!(s.done("a"), Some(k));
        }
        assert_eq!(s.done("a"), None);
        assert!(!s.busy("a") && s.busy("b"));
        assert_eq!(s.arrive("a", 5), Arrival::Now(5));
        assert_eq!(s.done("b"), None);
        assert_eq!(s.done("nobody"), None);
    }

    #[test]
    fn all_devices_together_are_bounded() {
        let mut s = Serial::default();
        let mut queued = 0;
        for d in 0..IN_ALL {
            let dev = d.to_string();
            assert_eq!(s.arrive(&dev, 0), Arrival::Now(0));
            if matches!(s.arrive(&dev, 1), Arrival::Queued) {
                queued += 1;
            }
        }
        assert_eq!(queued, IN_ALL);
        assert!(matches!(s.arrive("0", 2), Arrival::Full(2, 1)));
    }
}

//! The registry's devices: each in a slot of its own, found by id through a hash table,
//! or straight by its slot where the caller remembers it.
//!
//! A gateway's batch names the same plants in the same order every period, so the service
//! remembers, per position in a gateway's batch, the slot it found that position's device
//! in ([`Slot`]). Found by slot, a device costs no hash and no read of the table, whose
//! entries (the id and where the device lives) ten thousand devices take out of the caches
//! between one period and the next: that lookup was a fifth of the registry's time at ten
//! thousand devices (`docs/scale.md`, "The gateway path today"). A slot is only a hint: it
//! serves a device only if the slot holds that very id now. A device replaced under its
//! id takes its predecessor's slot (the hint then serves the new one, as the id would);
//! a slot remembered from before its device was removed holds nothing or another id, and
//! the caller looks the id up as before. Devices never move from their slot.

use std::collections::HashMap;

use super::device::{Device, ShortId};

/// Where a device lives in [`Devices`], as a caller remembers it; meaningful only with the
/// id it was found for.
pub type Slot = u32;

/// A device and its id, side by side: a slot's check of its id reads the line it reads
/// the device's pointer from.
#[derive(Debug)]
struct Entry {
    id: ShortId,
    device: Box<Device>,
}

/// Devices by id, each in a stable slot. Each device is boxed: the slots stay small (an id
/// inline and a pointer), and a move of one (a slot vector that grows) moves no state.
#[derive(Debug, Default)]
pub(super) struct Devices {
    /// Id to slot.
    index: HashMap<ShortId, Slot>,
    /// The slots; `None` where a device was removed, until a new one takes it.
    slots: Vec<Option<Entry>>,
    /// Empty slots, taken before the vector grows.
    free: Vec<Slot>,
}

impl Devices {
    pub(super) fn len(&self) -> usize {
        self.index.len()
    }

    pub(super) fn contains_key(&self, id: &str) -> bool {
        self.index.contains_key(id)
    }

    /// The slot `id` lives in, if served.
    pub(super) fn slot(&self, id: &str) -> Option<Slot> {
        self.index.get(id).copied()
    }

    // Found through the table, a slot holds the id by construction: not compared again.
    pub(super) fn get(&self, id: &str) -> Option<&Device> {
        let e = self.slots.get(self.slot(id)? as usize)?.as_ref()?;
        Some(&e.device)
    }

    pub(super) fn get_mut(&mut self, id: &str) -> Option<&mut Device> {
        let slot = self.slot(id)?;
        let e = self.slots.get_mut(slot as usize)?.as_mut()?;
        Some(&mut e.device)
    }

    /// The device served under `id`: from `slot` if that slot holds it now, else through
    /// the table, and `slot` set to where it was found (`None` if it is not served).
    pub(super) fn find(&self, slot: &mut Option<Slot>, id: &str) -> Option<&Device> {
        if let Some(d) = slot.and_then(|k| self.at(k, id)) {
            return Some(d);
        }
        // One hash: the slot found is read directly.
        *slot = self.slot(id);
        let e = self.slots.get((*slot)? as usize)?.as_ref()?;
        Some(&e.device)
    }

    /// [`Self::find`], mutable.
    pub(super) fn find_mut(&mut self, slot: &mut Option<Slot>, id: &str) -> Option<&mut Device> {
        if !slot.is_some_and(|k| self.at(k, id).is_some()) {
            *slot = self.slot(id);
        }
        let e = self.slots.get_mut((*slot)? as usize)?.as_mut()?;
        Some(&mut e.device)
    }

    /// The device in `slot`, if that slot holds `id` now (module documentation).
    pub(super) fn at(&self, slot: Slot, id: &str) -> Option<&Device> {
        match self.slots.get(slot as usize) {
            Some(Some(e)) if e.id.as_str() == id => Some(&e.device),
            _ => None,
        }
    }

    /// Serve `device` under `id`, in the slot of the device it replaces (returned) if
    /// there is one, else in a free slot.
    pub(super) fn insert(&mut self, id: ShortId, device: Box<Device>) -> Option<Box<Device>> {
        if let Some(&slot) = self.index.get(id.as_str()) {
            let old = self.slots[slot as usize].replace(Entry { id, device });
            return old.map(|e| e.device);
        }
        self.put(id, device);
        None
    }

    /// Serve `device` under `id`, which is not served yet, in a free slot (or a new one):
    /// its slot.
    fn put(&mut self, id: ShortId, device: Box<Device>) -> Slot {
        let slot = match self.free.pop() {
            Some(slot) => slot,
            None => {
                // More than four billion devices would need more than this machine's
                // memory many times over; the table is bounded far below
                // (`max_devices`).
                let slot = Slot::try_from(self.slots.len()).expect("fewer than 2^32 devices");
                self.slots.push(None);
                slot
            }
        };
        self.index.insert(id.clone(), slot);
        self.slots[slot as usize] = Some(Entry { id, device });
        slot
    }

    /// The device served under `id`, inserting `device` first if there is none.
    pub(super) fn or_insert(&mut self, id: ShortId, device: Box<Device>) -> &mut Device {
        let slot = match self.slot(id.as_str()) {
            Some(slot) => slot,
            None => self.put(id, device),
        };
        let e = self.slots[slot as usize].as_mut();
        // The table names only slots that hold their device.
        &mut e.expect("a slot the table names holds its device").device
    }

    pub(super) fn remove(&mut self, id: &str) -> Option<Box<Device>> {
        let slot = self.index.remove(id)?;
        let e = self.slots[slot as usize].take()?;
        self.free.push(slot);
        Some(e.device)
    }

    /// Every device with its id, in no particular order.
    pub(super) fn iter(&self) -> impl Iterator<Item = (&ShortId, &Device)> {
        self.slots.iter().flatten().map(|e| (&e.id, &*e.device))
    }

    pub(super) fn keys(&self) -> impl Iterator<Item = &ShortId> {
        self.index.keys()
    }

    pub(super) fn values_mut(&mut self) -> impl Iterator<Item = &mut Device> {
        self.slots.iter_mut().flatten().map(|e| &mut *e.device)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::DeviceChannel;

    fn device(home: u32) -> Box<Device> {
        let channels = [DeviceChannel {
            law: mfc::LawConfig::default(),
            output: mfc::OutputMapConfig::default(),
            reference: Vec::new(),
            envelope: None,
            bounds: Default::default(),
            range: None,
        }];
        let mut d = Device::new(&channels, Default::default(), false).unwrap();
        d.home = home;
        Box::new(d)
    }

    /// A slot serves only the id it holds now: after a removal, a replacement in another
    /// slot, or a new device in the freed slot, a remembered slot finds nothing (or not
    /// the device it was remembered for), and the id still finds its device.
    #[test]
    fn a_slot_serves_only_the_id_it_holds_now() {
        let mut t = Devices::default();
        assert!(t.insert(ShortId::new("a"), device(1)).is_none());
        assert!(t.insert(ShortId::new("b"), device(2)).is_none());
        let a = t.slot("a").unwrap();
        assert_eq!(t.at(a, "a").unwrap().home, 1);
        assert!(t.at(a, "b").is_none(), "a slot found for another id");
        // Replaced: the same slot, the new device.
        assert_eq!(t.insert(ShortId::new("a"), device(3)).unwrap().home, 1);
        assert_eq!(t.slot("a"), Some(a));
        assert_eq!(t.get_mut("a").unwrap().home, 3);
        // Removed, and the slot taken by another id.
        assert_eq!(t.remove("a").unwrap().home, 3);
        assert!(t.at(a, "a").is_none() && t.get("a").is_none());
        t.insert(ShortId::new("c"), device(4));
        assert_eq!(t.slot("c"), Some(a), "the free slot is taken first");
        assert!(t.at(a, "a").is_none());
        // Back, in a slot of its own.
        t.insert(ShortId::new("a"), device(5));
        let again = t.slot("a").unwrap();
        assert_ne!(again, a);
        assert_eq!(t.get("a").unwrap().home, 5);
        assert_eq!(t.len(), 3);
        let mut homes: Vec<u32> = t.iter().map(|(_, d)| d.home).collect();
        homes.sort_unstable();
        assert_eq!(homes, [2, 4, 5]);
        assert_eq!(t.or_insert(ShortId::new("b"), device(9)).home, 2);
        assert_eq!(t.or_insert(ShortId::new("d"), device(6)).home, 6);
        assert_eq!(t.len(), 4);
        assert_eq!(t.keys().count(), 4);
        assert_eq!(t.values_mut().count(), 4);
        assert!(t.remove("x").is_none());
        // Found by a stale slot: through the table, and the slot set again.
        let mut remembered = Some(a);
        assert_eq!(t.find(&mut remembered, "a").unwrap().home, 5);
        assert_eq!(remembered, Some(again));
        let mut remembered = Some(a);
        assert_eq!(t.find_mut(&mut remembered, "a").unwrap().home, 5);
        assert_eq!(remembered, Some(again));
        assert_eq!(t.find_mut(&mut remembered, "c").unwrap().home, 4);
        assert_eq!(remembered, Some(a));
        assert!(t.find(&mut remembered, "x").is_none());
        assert_eq!(remembered, None);
    }
}

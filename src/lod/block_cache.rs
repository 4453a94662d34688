//! A map of per-block results that depend on the terrain and the block's configuration
//! but not on the camera (stitched strips, edge regions, interior summaries), shared by
//! the draw thread's traversals. Bounded, so that a long flight cannot grow it without
//! end, in two generations: new entries go to the current one; when it is full it
//! becomes the previous one and the older entries are dropped; an entry found in the
//! previous generation moves back to the current one. So what the frames keep drawing
//! is never dropped and recomputed all at once (a frame draws a few thousand blocks at
//! most), and what they stopped drawing goes within two generations.

use std::hash::Hash;
use std::sync::Mutex;

/// Entries kept at most (both generations): a generation holds 4096, more than the
/// blocks of any frame (the 4k flyover's heaviest draws about 700). The largest value
/// kept, an edge region, is 648 bytes, so a map holds about 6 MB at most and the
/// traversal's four (strips, exact regions, their bounds, interiors) under 20 MB.
pub const CACHE_ENTRIES: usize = 1 << 13;

struct Generations<K, V> {
    current: foldhash::HashMap<K, V>,
    previous: foldhash::HashMap<K, V>,
    /// Entries a generation holds.
    generation: usize,
}

impl<K: Eq + Hash, V> Generations<K, V> {
    fn insert(&mut self, key: K, v: V) {
        if self.current.len() >= self.generation {
            self.previous = std::mem::take(&mut self.current);
        }
        self.current.insert(key, v);
    }
}

pub struct BoundedCache<K, V> {
    maps: Mutex<Generations<K, V>>,
}

impl<K, V> Default for BoundedCache<K, V> {
    fn default() -> Self {
        Self::with_entries(CACHE_ENTRIES)
    }
}

impl<K, V> BoundedCache<K, V> {
    /// A cache of at most `entries` (both generations): for frames that draw more blocks
    /// than [`CACHE_ENTRIES`] allows for (streamed frames to the horizon draw about 4,000).
    pub fn with_entries(entries: usize) -> Self {
        let maps =
            Generations { current: Default::default(), previous: Default::default(), generation: entries.max(2) / 2 };
        BoundedCache { maps: Mutex::new(maps) }
    }
}

impl<K: Clone, V: Clone> Clone for BoundedCache<K, V> {
    fn clone(&self) -> Self {
        let maps = self.lock();
        let maps =
            Generations { current: maps.current.clone(), previous: maps.previous.clone(), generation: maps.generation };
        BoundedCache { maps: Mutex::new(maps) }
    }
}

impl<K, V> std::fmt::Debug for BoundedCache<K, V> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "BoundedCache({} entries)", self.len())
    }
}

impl<K, V> BoundedCache<K, V> {
    /// A poisoned lock only means another thread panicked mid-insert; entries are whole
    /// values, so the maps are still consistent.
    fn lock(&self) -> std::sync::MutexGuard<'_, Generations<K, V>> {
        self.maps.lock().unwrap_or_else(|e| e.into_inner())
    }

    pub fn len(&self) -> usize {
        let maps = self.lock();
        maps.current.len() + maps.previous.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

impl<K: Eq + Hash, V: Copy> BoundedCache<K, V> {
    /// The value under `key`, computed (without the lock held) on first use.
    pub fn get_or_compute(&self, key: K, compute: impl FnOnce() -> V) -> V {
        {
            let mut maps = self.lock();
            if let Some(v) = maps.current.get(&key) {
                return *v;
            }
            if let Some(v) = maps.previous.remove(&key) {
                maps.insert(key, v);
                return v;
            }
        }
        let v = compute();
        self.lock().insert(key, v);
        v
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Computed once; never more than `CACHE_ENTRIES`; a key asked for between every
    /// few new ones (a block drawn every frame) is never dropped, however many pass
    /// through; one not asked for again is dropped within two generations.
    #[test]
    fn keeps_what_is_used_and_stays_bounded() {
        let cache = BoundedCache::default();
        let calls = std::cell::Cell::new(0);
        let counted = |v: u32| {
            calls.set(calls.get() + 1);
            v
        };
        assert_eq!(cache.get_or_compute(u32::MAX, || counted(10)), 10);
        assert_eq!(cache.get_or_compute(u32::MAX, || counted(20)), 10);
        assert_eq!(calls.get(), 1);
        for k in 0..3 * CACHE_ENTRIES as u32 {
            assert_eq!(cache.get_or_compute(k, || k), k);
            if k % 100 == 0 {
                assert_eq!(cache.get_or_compute(u32::MAX, || counted(30)), 10);
            }
            assert!(cache.len() <= CACHE_ENTRIES);
        }
        assert_eq!(calls.get(), 1, "the key in use was dropped");
        // Key 7 has not been asked for since the first generation.
        assert_eq!(cache.get_or_compute(7, || 99), 99);
    }
}

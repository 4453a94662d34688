//! A map of per-block results that depend on the terrain and the block's configuration
//! but not on the camera (stitched strips, edge regions, interior summaries), shared by
//! the draw thread's traversals. Bounded, so that a long flight cannot grow it without
//! end: a frame draws a few thousand blocks at most, and the map keeps several frames'
//! worth before it is emptied and refilled.

use std::hash::Hash;
use std::sync::Mutex;

/// Entries kept before the map is emptied.
pub const CACHE_ENTRIES: usize = 1 << 14;

pub struct BoundedCache<K, V> {
    map: Mutex<foldhash::HashMap<K, V>>,
}

impl<K, V> Default for BoundedCache<K, V> {
    fn default() -> Self {
        BoundedCache { map: Mutex::new(foldhash::HashMap::default()) }
    }
}

impl<K: Clone, V: Clone> Clone for BoundedCache<K, V> {
    fn clone(&self) -> Self {
        BoundedCache { map: Mutex::new(self.lock().clone()) }
    }
}

impl<K, V> std::fmt::Debug for BoundedCache<K, V> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "BoundedCache({} entries)", self.len())
    }
}

impl<K, V> BoundedCache<K, V> {
    /// A poisoned lock only means another thread panicked mid-insert; entries are whole
    /// values, so the map is still consistent.
    fn lock(&self) -> std::sync::MutexGuard<'_, foldhash::HashMap<K, V>> {
        self.map.lock().unwrap_or_else(|e| e.into_inner())
    }

    pub fn len(&self) -> usize {
        self.lock().len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

impl<K: Eq + Hash, V: Copy> BoundedCache<K, V> {
    /// The value under `key`, computed (without the lock held) on first use.
    pub fn get_or_compute(&self, key: K, compute: impl FnOnce() -> V) -> V {
        if let Some(v) = self.lock().get(&key) {
            return *v;
        }
        let v = compute();
        let mut map = self.lock();
        if map.len() >= CACHE_ENTRIES {
            map.clear();
        }
        map.insert(key, v);
        v
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn computes_once_and_stays_bounded() {
        let cache = BoundedCache::default();
        let mut calls = 0;
        assert_eq!(
            cache.get_or_compute(1u32, || {
                calls += 1;
                10u32
            }),
            10
        );
        assert_eq!(
            cache.get_or_compute(1u32, || {
                calls += 1;
                20u32
            }),
            10
        );
        assert_eq!(calls, 1);
        for k in 0..3 * CACHE_ENTRIES as u32 {
            cache.get_or_compute(k, || k);
            assert!(cache.len() <= CACHE_ENTRIES);
        }
        // Full again (keys 2C..3C): key 7 was dropped with an earlier fill, and adding it
        // empties the map first.
        assert_eq!(cache.len(), CACHE_ENTRIES);
        assert_eq!(cache.get_or_compute(7, || 99), 99);
        assert_eq!(cache.len(), 1);
    }
}

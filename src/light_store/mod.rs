//! Diffuse radiance stored per node (004 §4.6) and the push-pull that keeps levels
//! consistent (§4.8).
//!
//! State lives here, keyed by the node's global number, never in the pages: evicting a page
//! loses nothing (FORMAT.md keeps the node's illumination fields for baked archives only).
//! What is stored is the cosine-weighted incident radiance E/π, not ρ·E/π as in the thesis,
//! so the hit triangle's own albedo multiplies it: a leaf mixes up to 8 triangles and their
//! materials, and the average incident light is what they share.

pub mod file;
mod keys;
mod pull;

pub use keys::{tri_area, Keys, CELLS, CELL_FRACTION, GRID};
pub use pull::pull;

use crate::paging::PageCache;
use rustc_hash::{FxHashMap, FxHashSet};
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering::Relaxed};
use std::sync::{Arc, Mutex};

const SHARDS: usize = 64;

/// One node's accumulated samples.
#[derive(Clone, Copy, Debug, Default)]
pub struct Entry {
    /// Σ β·L: samples weighted by the throughput of the path that took them.
    pub sum: [f32; 3],
    /// Σ β.
    pub weight: f32,
    pub n: u32,
    /// Area-weighted average of the children (after a pull) and the samples behind it.
    pub pulled: [f32; 3],
    pub pulled_n: u32,
    /// Caustic light from the light pass (004 §4.7), times the photons emitted so far:
    /// Σ Φ/(π·A') for a triangle cell, the children's area-weighted mean for a node.
    pub caustic: [f32; 3],
    /// Visible fraction of a cell's area (§4.7.1); 0 until estimated.
    pub visible: f32,
}

impl Entry {
    /// The best estimate: own samples, or the children's when they hold more.
    pub fn value(&self) -> Option<([f32; 3], u32)> {
        if self.pulled_n > self.n {
            Some((self.pulled, self.pulled_n))
        } else if self.n > 0 {
            self.mean().map(|m| (m, self.n))
        } else {
            None
        }
    }

    /// The throughput-weighted mean of the own samples.
    fn mean(&self) -> Option<[f32; 3]> {
        (self.weight > 0.0).then(|| self.sum.map(|v| v / self.weight))
    }
}

/// One shard of the store: its entries, and the blocks (a node's own key and its cells'
/// keys) holding any of them.
#[derive(Default)]
struct Shard {
    map: FxHashMap<u64, Entry>,
    blocks: FxHashSet<u64>,
    /// Reads of a mean (`read`) and samples counted (`add`), for the reuse figure.
    reads: u64,
    adds: u64,
}

/// Concurrent map from key to entry (sharded mutexes; a block's keys share a shard).
pub struct RadianceStore {
    shards: Vec<Mutex<Shard>>,
    /// Keys per block (`Keys::block`).
    block: u64,
    /// Samples after which a node counts as converged (004 §4.6.1 used 65536).
    pub limit: u32,
    /// Most entries the memory budget allows; nodes met after that are not stored (their
    /// samples still reach the image), and nothing stored is ever dropped.
    max_entries: usize,
    entries: AtomicUsize,
    refused: AtomicU64,
    /// Photons the light pass has emitted in all (M of 004 eq. 4.29).
    photons: AtomicU64,
    /// Per page: whether stored light under it changed since the last pull.
    dirty: Vec<AtomicBool>,
    /// The same for the pages of prototypes, per instance: (instance, page) → the instance
    /// leaf's global number and the global numbers of the page's nodes whose light changed.
    placed_dirty: Mutex<HashMap<(u32, u32), Placed>>,
    /// The page cache the store's bytes are charged to as it grows (`charging`).
    cache: Option<Arc<PageCache>>,
}

/// What changed in a prototype's page as an instance places it: the instance leaf's global
/// number, and the page's nodes (global numbers) whose stored light changed.
pub type Placed = (u64, Vec<u64>);

/// Entries charged to the page cache at a time (80 KiB).
const CHARGE_ENTRIES: usize = 1024;

/// Bytes an entry costs in the map: 8-byte key and 52-byte entry, hash-table overhead at
/// its 7/8 load factor and one control byte; and at most one block marker (8-byte key, the
/// same overhead).
pub const ENTRY_BYTES: u64 = 80;

impl RadianceStore {
    /// `max_bytes`: the store's share of the memory budget (None: unbounded); `pages`: the
    /// archive's page count; `block`: keys per block (`Keys::block`).
    pub fn new(limit: u32, max_bytes: Option<u64>, pages: usize, block: u64) -> RadianceStore {
        RadianceStore {
            shards: (0..SHARDS).map(|_| Mutex::default()).collect(),
            block: block.max(1),
            limit: limit.max(1),
            max_entries: max_bytes.map_or(usize::MAX, |b| (b / ENTRY_BYTES) as usize),
            entries: AtomicUsize::new(0),
            refused: AtomicU64::new(0),
            photons: AtomicU64::new(0),
            dirty: (0..pages).map(|_| AtomicBool::new(false)).collect(),
            placed_dirty: Mutex::new(HashMap::new()),
            cache: None,
        }
    }

    /// The store, its bytes taken from the share `cache` was lent for them
    /// (`PageCache::lending`) as it grows, `CHARGE_ENTRIES` entries ahead.
    pub fn charging(self, cache: Arc<PageCache>) -> RadianceStore {
        RadianceStore {
            cache: Some(cache),
            ..self
        }
    }

    /// Notes that the stored light of `node` (a global number) in `page` changed, there as
    /// placed by `instance` through its leaf `via` (`NO_INSTANCE`: a page of the scene's own
    /// tree, whose pull takes the whole page).
    pub fn mark_dirty_in(&self, instance: u32, page: u32, via: u64, node: u64) {
        match instance {
            crate::trace::NO_INSTANCE => self.mark_dirty(page),
            i => {
                let mut d = self.placed_dirty.lock().expect("dirty");
                let (_, nodes) = d.entry((i, page)).or_insert((via, Vec::new()));
                if !nodes.contains(&node) {
                    nodes.push(node);
                }
            }
        }
    }

    /// The prototype pages marked since the last call, by instance: (instance, page,
    /// what changed there).
    pub fn take_placed_dirty(&self) -> Vec<(u32, u32, Placed)> {
        let mut v: Vec<_> = std::mem::take(&mut *self.placed_dirty.lock().expect("dirty"))
            .into_iter()
            .map(|((i, p), placed)| (i, p, placed))
            .collect();
        v.sort_unstable_by_key(|&(i, p, _)| (i, p));
        v
    }

    /// Notes that stored light under `page` changed.
    pub fn mark_dirty(&self, page: u32) {
        if let Some(d) = self.dirty.get(page as usize) {
            d.store(true, Relaxed);
        }
    }

    /// The pages marked since the last call, in page order.
    pub fn take_dirty(&self) -> Vec<u32> {
        (0..self.dirty.len() as u32)
            .filter(|&i| self.dirty[i as usize].swap(false, Relaxed))
            .collect()
    }

    /// The entry for `node`, created if the budget has room.
    fn entry<'m>(&self, m: &'m mut Shard, node: u64) -> Option<&'m mut Entry> {
        if !m.map.contains_key(&node) {
            if self.entries.load(Relaxed) >= self.max_entries {
                self.refused.fetch_add(1, Relaxed);
                return None;
            }
            let n = self.entries.fetch_add(1, Relaxed);
            if let Some(cache) = self
                .cache
                .as_ref()
                .filter(|_| n.is_multiple_of(CHARGE_ENTRIES))
            {
                cache.charge(CHARGE_ENTRIES as u64 * ENTRY_BYTES);
            }
            m.blocks.insert(node / self.block);
        }
        Some(m.map.entry(node).or_default())
    }

    /// Whether any key of the block starting at `node` (a node's own key, `Keys::node`) has
    /// an entry: a leaf whose triangles hold no light is skipped by the pull at one lookup.
    pub fn lit(&self, node: u64) -> bool {
        let b = node / self.block;
        self.shard(node).lock().expect("store").blocks.contains(&b)
    }

    /// Samples not stored because the budget was full.
    pub fn refused(&self) -> u64 {
        self.refused.load(Relaxed)
    }

    fn shard(&self, node: u64) -> &Mutex<Shard> {
        let b = node / self.block;
        &self.shards[(b.wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 58) as usize % SHARDS]
    }

    /// The entry for `node`, counted as a read of its mean.
    pub fn read(&self, node: u64) -> Option<Entry> {
        self.lookup(node, true)
    }

    /// Reads of a mean and samples counted so far (the mean's reuse is their ratio).
    pub fn reuse(&self) -> [u64; 2] {
        self.shards.iter().fold([0, 0], |[r, a], s| {
            let m = s.lock().expect("store");
            [r + m.reads, a + m.adds]
        })
    }

    pub fn get(&self, node: u64) -> Option<Entry> {
        self.lookup(node, false)
    }

    fn lookup(&self, node: u64, read: bool) -> Option<Entry> {
        let mut m = self.shard(node).lock().expect("store");
        m.reads += u64::from(read);
        m.map.get(&node).copied()
    }

    /// Adds a sample taken by a path of throughput `beta` (unless the node has converged)
    /// and returns the node's mean after it (004 eq. 4.24–4.25) and whether it has
    /// converged.
    pub fn add(&self, node: u64, sample: [f32; 3], beta: f32) -> ([f32; 3], bool) {
        let mut m = self.shard(node).lock().expect("store");
        let Some(e) = self.entry(&mut m, node) else {
            return (sample, false);
        };
        let usable = beta.is_finite() && beta > 0.0 && sample.iter().all(|v| v.is_finite());
        let counted = usable && e.n < self.limit;
        if counted {
            add_to(&mut e.sum, sample.map(|x| beta * x));
            e.weight += beta;
            e.n += 1;
        }
        // A node with nothing counted yet answers with the sample, as it would have
        // without the store (a non-finite part as 0).
        let avg = e
            .mean()
            .unwrap_or(sample.map(|v| if v.is_finite() { v } else { 0.0 }));
        let converged = e.n >= self.limit;
        m.adds += u64::from(counted);
        (avg, converged)
    }

    /// Runs `f` on the node's entry, created if the budget has room.
    fn update(&self, node: u64, f: impl FnOnce(&mut Entry)) {
        let mut m = self.shard(node).lock().expect("store");
        if let Some(e) = self.entry(&mut m, node) {
            f(e);
        }
    }

    /// Sets a node's pulled value.
    pub fn set_pulled(&self, node: u64, value: [f32; 3], n: u32) {
        self.update(node, |e| {
            e.pulled = value;
            e.pulled_n = n;
        });
    }

    /// Adds a photon's caustic contribution to a cell (non-finite ones are dropped).
    pub fn add_caustic(&self, cell: u64, v: [f32; 3]) {
        if v.iter().all(|x| x.is_finite()) {
            self.update(cell, |e| add_to(&mut e.caustic, v));
        }
    }

    /// Sets a node's caustic light (the pull's area-weighted mean of its children).
    pub fn set_caustic(&self, node: u64, v: [f32; 3]) {
        self.update(node, |e| e.caustic = v);
    }

    pub fn set_visible(&self, cell: u64, fraction: f32) {
        self.update(cell, |e| e.visible = fraction);
    }

    /// Caustic light arriving at an entry's cell or node as E/π, like the diffuse store's
    /// values (None before any light pass).
    pub fn caustic(&self, e: &Entry) -> Option<[f32; 3]> {
        let m = self.photons.load(Relaxed);
        (m > 0).then(|| e.caustic.map(|c| c / m as f32))
    }

    pub fn add_photons(&self, n: u64) {
        self.photons.fetch_add(n, Relaxed);
    }

    pub fn photons(&self) -> u64 {
        self.photons.load(Relaxed)
    }

    pub fn len(&self) -> usize {
        self.shards
            .iter()
            .map(|s| s.lock().expect("store").map.len())
            .sum()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    pub fn bytes(&self) -> u64 {
        self.len() as u64 * ENTRY_BYTES
    }

    /// Every entry, by key.
    pub fn sorted(&self) -> Vec<(u64, Entry)> {
        let mut all: Vec<(u64, Entry)> = self
            .shards
            .iter()
            .flat_map(|s| {
                let m = s.lock().expect("store");
                m.map.iter().map(|(k, e)| (*k, *e)).collect::<Vec<_>>()
            })
            .collect();
        all.sort_unstable_by_key(|(k, _)| *k);
        all
    }

    /// Starts from saved entries and photon count (`file::load`); None if the budget's
    /// share cannot hold them.
    pub fn restore(&self, entries: Vec<(u64, Entry)>, photons: u64) -> Option<()> {
        if entries.len() > self.max_entries {
            return None;
        }
        for (k, e) in entries {
            let mut m = self.shard(k).lock().expect("store");
            m.blocks.insert(k / self.block);
            if m.map.insert(k, e).is_none() {
                self.entries.fetch_add(1, Relaxed);
            }
        }
        self.photons.store(photons, Relaxed);
        Some(())
    }

    /// Entries the budget's share allows.
    pub fn capacity(&self) -> usize {
        self.max_entries
    }

    /// Nodes whose counter reached the limit.
    pub fn converged(&self) -> usize {
        self.shards
            .iter()
            .map(|s| {
                s.lock()
                    .expect("store")
                    .map
                    .values()
                    .filter(|e| e.n >= self.limit)
                    .count()
            })
            .sum()
    }
}

fn add_to(sum: &mut [f32; 3], v: [f32; 3]) {
    for (s, x) in sum.iter_mut().zip(v) {
        *s += x;
    }
}

/// Mean of values under weights (areas, sample counts); None when the weights sum to zero.
pub fn weighted_mean(items: impl IntoIterator<Item = ([f32; 3], f32)>) -> Option<[f32; 3]> {
    let (mut sum, mut total) = ([0f32; 3], 0f32);
    for (v, w) in items {
        for (s, x) in sum.iter_mut().zip(v) {
            *s += x * w;
        }
        total += w;
    }
    (total > 0.0).then(|| sum.map(|s| s / total))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counter_saturates_and_stops_accumulating() {
        let s = RadianceStore::new(4, None, 0, 1);
        for i in 0..10 {
            let (avg, conv) = s.add(7, [i as f32; 3], 1.0);
            assert_eq!(conv, i >= 3, "sample {i}");
            // Samples past the limit are ignored: the mean stays that of the first four.
            if i >= 3 {
                assert_eq!(avg, [1.5; 3]);
            }
        }
        assert_eq!(s.get(7).unwrap().n, 4);
        assert_eq!(s.converged(), 1);
        // A non-finite sample is dropped rather than poisoning the node.
        let (avg, _) = s.add(8, [f32::NAN, 1.0, 1.0], 1.0);
        assert!(avg.iter().all(|v| v.is_finite()));
    }

    #[test]
    fn samples_count_by_their_paths_throughput() {
        let s = RadianceStore::new(8, None, 0, 1);
        s.add(1, [1.0; 3], 0.25);
        // A sample whose path carries no throughput, or an unusable one, is not counted.
        for beta in [0.0, -1.0, f32::NAN] {
            s.add(1, [100.0; 3], beta);
        }
        let (avg, _) = s.add(1, [3.0; 3], 0.75);
        assert_eq!(avg, [2.5; 3]);
        let e = s.get(1).unwrap();
        assert_eq!((e.n, e.weight), (2, 1.0));
        assert_eq!(e.value(), Some(([2.5; 3], 2)));
    }

    /// A store charging the page cache takes its bytes out of the pages' budget as it
    /// grows, a block of entries ahead and never past the share lent, and the cache
    /// evicts pages to stay within its budget.
    #[test]
    fn a_charging_store_takes_its_bytes_back_from_the_page_cache() {
        let dir = tempfile::tempdir().unwrap();
        let archive = pull::tests::bunny_archive(dir.path());
        let load_all = |cache: &PageCache| {
            for pg in 0..archive.page_count() {
                cache.get(pg);
            }
            cache.resident_bytes()
        };
        let all = load_all(&PageCache::new(Arc::clone(&archive), None, 1).unwrap());
        let block = CHARGE_ENTRIES as u64 * ENTRY_BYTES;
        let lent = 3 * block;
        let cache = PageCache::lending(Arc::clone(&archive), Some(all - block), lent, 1).unwrap();
        // Every page fits while the lent share is unused.
        assert_eq!(load_all(&cache), all);
        assert_eq!(cache.stats().pages_evicted, 0);
        let store = RadianceStore::new(100, Some(lent), 0, 1).charging(Arc::clone(&cache));
        store.add(0, [1.0; 3], 1.0);
        assert_eq!(cache.charged(), block, "the first entry charges a block");
        assert_eq!(cache.stats().pages_evicted, 0);
        let entries = 3 * CHARGE_ENTRIES as u64;
        for key in 1..entries + 5 {
            store.add(key, [1.0; 3], 1.0);
        }
        assert_eq!(store.refused(), 5, "the share holds {entries} entries");
        assert_eq!(cache.charged(), lent, "charged past the share lent");
        assert!(cache.stats().pages_evicted > 0, "no page made room");
        assert!(
            cache.resident_bytes() <= all - block + lent,
            "{} resident, over the budget {}",
            cache.resident_bytes(),
            all - block + lent
        );
    }

    #[test]
    fn a_full_store_keeps_what_it_has_and_refuses_new_nodes() {
        let s = RadianceStore::new(100, Some(2 * ENTRY_BYTES), 0, 1);
        s.add(1, [1.0; 3], 1.0);
        s.add(2, [2.0; 3], 1.0);
        // A third node does not fit: its sample comes back unstored.
        assert_eq!(s.add(3, [5.0; 3], 1.0), ([5.0; 3], false));
        assert!(s.get(3).is_none());
        assert_eq!(s.refused(), 1);
        // Stored nodes keep accumulating.
        assert_eq!(s.add(1, [3.0; 3], 1.0).0, [2.0; 3]);
        assert_eq!(s.len(), 2);
    }
}

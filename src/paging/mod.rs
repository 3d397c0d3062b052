//! Decoded pages under a byte budget.
//!
//! Every page of the archive has a slot. A hit takes the slot's read lock and clones an
//! `Arc`; there is no global lock on that path. A miss decodes the page (outside any lock),
//! then makes room with CLOCK: the hand sweeps the slots, clearing reference bits and
//! evicting unpinned pages whose bit is clear. The top pages (levels below `PIN_LEVELS`)
//! are pinned. A page still referenced by a traversal when it is evicted stays alive until
//! that traversal drops it, so the budget can be exceeded by at most the pages the workers
//! are holding (a few per thread).
//!
//! A page that fails to decode (corrupt archive) is recorded as the cache's error and served
//! as an empty page, so traversal never panics; the renderer checks `error()` and fails.
//! Background prefetch: `prefetch` queues a page for a loader thread (crossbeam channel).
//!
//! A bake file (`canopy bake`) can be attached: each page then also carries its block
//! of baked node light, loaded, counted against the budget and evicted with it.

pub mod coefs;
pub mod instance;
mod page;
pub mod wide;

pub use page::{deepest_first, in_scene_tree, Corners, NodeRef, Page, TNode, TriW, WHITE};

use anyhow::{bail, Result};
use canopy_format::bake::{BakeFile, BakedBlock};
use canopy_format::{Archive, Node, NodeFlags, PageEntry, Tri};
use crossbeam_channel::{Receiver, Sender, TrySendError};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, Mutex, RwLock};

/// Evictions between returning freed heap memory to the system.
#[cfg(target_os = "linux")]
const TRIM_EVERY: u64 = 1024;

/// Pages this many levels from the root are pinned.
pub const PIN_LEVELS: u16 = 2;

/// The background loader of [`PageCache::start_prefetch`]: dropping it ends the loader
/// (its queue is closed and drained) and waits for its thread.
pub struct Prefetcher {
    cache: Arc<PageCache>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Drop for Prefetcher {
    fn drop(&mut self) {
        self.cache.prefetch_tx.lock().expect("prefetch lock").take();
        if let Some(t) = self.thread.take() {
            t.join().ok();
        }
    }
}

#[derive(Default)]
struct Slot {
    page: RwLock<Option<Arc<Page>>>,
    referenced: AtomicBool,
    pinned: bool,
}

/// A decoded texture tile: `TILE_BYTES` of RGBA8.
pub type TileData = Arc<Vec<u8>>;

#[derive(Default)]
struct TileSlot {
    data: RwLock<Option<TileData>>,
    referenced: AtomicBool,
}

/// Bytes a resident tile counts against the budget (texels and bookkeeping).
const TILE_COST: u64 = canopy_format::TILE_BYTES as u64 + 64;

/// Cache counters, read at the end of a render.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct CacheStats {
    pub pages_loaded: u64,
    pub pages_evicted: u64,
    #[serde(rename = "page_hits")]
    pub hits: u64,
    #[serde(rename = "page_misses")]
    pub misses: u64,
    pub bytes_decoded: u64,
    pub resident_bytes_peak: u64,
    pub pinned_bytes: u64,
    pub pages_touched: u64,
    pub page_hit_rate: f64,
    pub texture_tiles_loaded: u64,
    pub texture_tiles_evicted: u64,
    /// Decoded texture bytes resident at the end, and at most.
    pub texture_bytes_resident: u64,
    pub texture_bytes_peak: u64,
    /// Tiles loaded per MIP level (index = level), over all textures.
    pub texture_tiles_loaded_per_level: Vec<u64>,
}

pub struct PageCache {
    pub archive: Arc<Archive>,
    /// The page table, each entry checked, read once when the cache starts (a renderer
    /// needs every page's level and size to pin and budget; opening the archive does not).
    pub entries: Vec<PageEntry>,
    slots: Vec<Slot>,
    tiles: Vec<TileSlot>,
    /// MIP level of each tile, for the stats.
    tile_level: Vec<u8>,
    tile_loads: Vec<AtomicU64>,
    tile_evictions: AtomicU64,
    tile_resident: AtomicU64,
    tile_resident_peak: AtomicU64,
    /// Pages' bytes at most, with the lent bytes the integrator's state has not taken back.
    budget: u64,
    /// Bytes of the budget lent by the integrator's state, and those it took back.
    lent: u64,
    charged: AtomicU64,
    /// How the command's `--mem-budget` was split to give `budget`, for errors.
    budget_note: std::sync::OnceLock<String>,
    /// Worker threads the minimum budget was computed for.
    threads: usize,
    resident: AtomicU64,
    resident_peak: AtomicU64,
    pinned_bytes: u64,
    hand: Mutex<usize>,
    epoch: AtomicU64,
    loads: AtomicU64,
    evictions: AtomicU64,
    hits: AtomicU64,
    misses: AtomicU64,
    decoded: AtomicU64,
    touched: Vec<AtomicBool>,
    error: Mutex<Option<String>>,
    prefetch_tx: Mutex<Option<Sender<u32>>>,
    sidecar: RwLock<Option<Arc<BakeFile>>>,
    /// Moves when a bake file is attached: a load that began before does not store
    /// its page.
    sidecar_gen: AtomicU64,
}

/// glibc gives each thread its own heap arena, and a page freed in one arena is not reused
/// by another thread's loads: under a budget with constant eviction, peak RSS was 6–16%
/// past the budget (b20, PBGI, 2 threads) and 6% under it with one arena. Takes effect only
/// before any thread but main has allocated, so `main` calls it first when a budget is set.
pub fn one_arena() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only sets an allocator tunable.
    unsafe {
        libc::mallopt(libc::M_ARENA_MAX, 1);
    }
}

/// Decoded size of a page without decoding it (from its page-table counts).
pub fn decoded_size(archive: &Archive, e: &PageEntry) -> u64 {
    let streams = canopy_format::Streams::of(archive.header.features);
    let per_tri = std::mem::size_of::<TriW>()
        + 12 * streams.normals as usize
        + 24 * streams.uv_sets() as usize
        + 24 * streams.colours as usize;
    (std::mem::size_of::<Page>()
        + e.node_count as usize * (std::mem::size_of::<Node>() + std::mem::size_of::<TNode>())
        + e.tri_count as usize * per_tri) as u64
}

impl PageCache {
    /// Pins and loads the top pages. `budget` bounds decoded pages (None: unlimited); a
    /// budget that cannot hold the pinned pages plus a working set is an error naming the
    /// minimum.
    pub fn new(archive: Arc<Archive>, budget: Option<u64>, threads: usize) -> Result<Arc<Self>> {
        Self::lending(archive, budget, 0, threads)
    }

    /// As `new`, with `lent` bytes more that the integrator's state takes back as it grows
    /// (`charge`): the pages use them until then. `budget` alone must hold the minimum.
    pub fn lending(
        archive: Arc<Archive>,
        budget: Option<u64>,
        lent: u64,
        threads: usize,
    ) -> Result<Arc<Self>> {
        let entries = archive.entries()?;
        let n = entries.len();
        let slots: Vec<Slot> = entries
            .iter()
            .map(|e| Slot {
                pinned: e.level < PIN_LEVELS,
                ..Default::default()
            })
            .collect();
        let pinned: u64 = entries
            .iter()
            .filter(|e| e.level < PIN_LEVELS)
            .map(|e| decoded_size(&archive, e))
            .sum();
        let largest = entries
            .iter()
            .map(|e| decoded_size(&archive, e))
            .max()
            .unwrap_or(0);
        let minimum = Self::minimum(pinned, largest, threads);
        if let Some(b) = budget {
            if b < minimum {
                bail!(
                    "the page cache's {} is too small for {}: the pinned top pages take {:.1} MiB and each of {threads} threads needs room for a path of pages; the minimum is {:.1} MiB",
                    crate::units::format_size(b),
                    archive.path().display(),
                    pinned as f64 / 1048576.0,
                    minimum as f64 / 1048576.0,
                );
            }
        }
        let mut tile_level = Vec::with_capacity(archive.tile_count() as usize);
        for t in &archive.textures {
            for (l, run) in t.level_first_tiles().windows(2).enumerate() {
                tile_level.extend(std::iter::repeat_n(l as u8, (run[1] - run[0]) as usize));
            }
        }
        let cache = Arc::new(PageCache {
            tiles: (0..tile_level.len()).map(|_| TileSlot::default()).collect(),
            tile_loads: (0..32).map(|_| AtomicU64::new(0)).collect(),
            tile_level,
            tile_evictions: AtomicU64::new(0),
            tile_resident: AtomicU64::new(0),
            tile_resident_peak: AtomicU64::new(0),
            entries,
            slots,
            budget: budget.map_or(u64::MAX, |b| b + lent),
            lent: budget.map_or(0, |_| lent),
            charged: AtomicU64::new(0),
            budget_note: std::sync::OnceLock::new(),
            threads,
            resident: AtomicU64::new(0),
            resident_peak: AtomicU64::new(0),
            pinned_bytes: pinned,
            hand: Mutex::new(0),
            epoch: AtomicU64::new(0),
            loads: AtomicU64::new(0),
            evictions: AtomicU64::new(0),
            hits: AtomicU64::new(0),
            misses: AtomicU64::new(0),
            decoded: AtomicU64::new(0),
            touched: (0..n).map(|_| AtomicBool::new(false)).collect(),
            error: Mutex::new(None),
            prefetch_tx: Mutex::new(None),
            sidecar: RwLock::new(None),
            sidecar_gen: AtomicU64::new(0),
            archive,
        });
        for i in 0..n as u32 {
            if cache.slots[i as usize].pinned {
                cache.load(i);
            }
        }
        if let Some(e) = cache.error() {
            bail!(e);
        }
        Ok(cache)
    }

    /// Smallest budget accepted: the pinned pages plus, per thread, a root-to-leaf path of
    /// the largest pages (16 levels) so concurrent traversals do not thrash.
    pub fn minimum(pinned: u64, largest: u64, threads: usize) -> u64 {
        pinned + threads as u64 * 16 * largest
    }

    /// Starts the background loader; `prefetch` is a no-op until this is called. The
    /// loader runs until the returned guard is dropped (on every path out of a render,
    /// errors included: the loader holds the cache, so a loader left running would keep
    /// it, and its thread, alive).
    pub fn start_prefetch(self: &Arc<Self>) -> Prefetcher {
        let (tx, rx): (Sender<u32>, Receiver<u32>) = crossbeam_channel::bounded(256);
        *self.prefetch_tx.lock().expect("prefetch lock") = Some(tx);
        let me = Arc::clone(self);
        let thread = std::thread::spawn(move || {
            for id in rx {
                if me.slots[id as usize].page.read().expect("slot").is_none() {
                    me.load(id);
                }
            }
        });
        Prefetcher {
            cache: Arc::clone(self),
            thread: Some(thread),
        }
    }

    /// Queues a page for the background loader unless it is resident or the queue is full.
    pub fn prefetch(&self, id: u32) {
        if self.slots[id as usize].page.read().expect("slot").is_some() {
            return;
        }
        if let Some(tx) = self.prefetch_tx.lock().expect("prefetch lock").as_ref() {
            // A full queue drops the hint: the page is then loaded on demand.
            let _: Result<(), TrySendError<u32>> = tx.try_send(id);
        }
    }

    /// The page, loading it if needed.
    #[inline]
    pub fn get(&self, id: u32) -> Arc<Page> {
        let slot = &self.slots[id as usize];
        // Pages a traversal asked for (not those only prefetched).
        if !self.touched[id as usize].load(Relaxed) {
            self.touched[id as usize].store(true, Relaxed);
        }
        if let Some(p) = slot.page.read().expect("slot").as_ref() {
            if !slot.referenced.load(Relaxed) {
                slot.referenced.store(true, Relaxed);
            }
            return Arc::clone(p);
        }
        self.misses.fetch_add(1, Relaxed);
        let page = self.load(id);
        // Children of a page just needed are likely next; hint them while a finite budget
        // has room (without a budget, speculation would only grow memory).
        if self.budget != u64::MAX && self.resident.load(Relaxed) < self.budget / 4 * 3 {
            for n in &page.bvh {
                if let NodeRef::ChildPage(c) = n.link() {
                    self.prefetch(c);
                }
            }
        }
        page
    }

    /// Attaches baked light: every resident page is dropped (pinned pages are loaded again)
    /// so each page holds its block from now on. Call it while no traversal runs. A budget
    /// that cannot hold the pinned pages with their blocks and, per worker, the largest page
    /// with its block is an error naming the minimum, before any block is read.
    /// Records how the command's `--mem-budget` was split to give the cache's budget; a
    /// budget too small for a bake then says so.
    pub fn note_budget(&self, note: String) {
        let _ = self.budget_note.set(note);
    }

    pub fn attach_bake(&self, r: BakeFile) -> Result<()> {
        if self.budget != u64::MAX {
            let with_block = |i: usize| {
                decoded_size(&self.archive, &self.entries[i]) + r.blocks[i].raw_len as u64
            };
            let pinned: u64 = (0..self.entries.len())
                .filter(|&i| self.slots[i].pinned)
                .map(with_block)
                .sum();
            let largest = (0..self.entries.len()).map(with_block).max().unwrap_or(0);
            // Each worker holds at least one page with its block; the path of pages that
            // `minimum` reserves per worker was already checked without the blocks.
            let minimum = pinned + self.threads as u64 * largest;
            if self.budget < minimum {
                bail!(
                    "the page cache's {} is too small for {} with its baked light {}: the pinned top pages and their blocks take {:.1} MiB and the largest page with its block {:.1} MiB; the minimum is {:.1} MiB{}",
                    crate::units::format_size(self.budget),
                    self.archive.path().display(),
                    r.path().display(),
                    pinned as f64 / 1048576.0,
                    largest as f64 / 1048576.0,
                    minimum as f64 / 1048576.0,
                    self.budget_note.get().map_or(String::new(), |n| format!(" ({n})")),
                );
            }
        }
        *self.sidecar.write().expect("sidecar") = Some(Arc::new(r));
        self.sidecar_gen.fetch_add(1, Relaxed);
        for slot in &self.slots {
            if let Some(p) = slot.page.write().expect("slot").take() {
                self.resident.fetch_sub(p.bytes, Relaxed);
            }
        }
        self.epoch.fetch_add(1, Relaxed);
        for i in 0..self.slots.len() as u32 {
            if self.slots[i as usize].pinned {
                self.load(i);
            }
        }
        match self.error() {
            Some(e) => bail!(e),
            None => Ok(()),
        }
    }

    fn decode(&self, id: u32) -> Result<Page> {
        let page = Page::decode(&self.archive, id)?;
        match self.sidecar.read().expect("sidecar").as_deref() {
            Some(r) => page.with_baked(r),
            None => Ok(page),
        }
    }

    fn load(&self, id: u32) -> Arc<Page> {
        let generation = self.sidecar_gen.load(Relaxed);
        let page = match self.decode(id) {
            Ok(p) => p,
            Err(e) => {
                self.record_error(&e);
                Page::empty(id)
            }
        };
        let page = Arc::new(page);
        let slot = &self.slots[id as usize];
        {
            let mut w = slot.page.write().expect("slot");
            if let Some(p) = w.as_ref() {
                return Arc::clone(p);
            }
            if self.sidecar_gen.load(Relaxed) != generation {
                return page;
            }
            *w = Some(Arc::clone(&page));
        }
        slot.referenced.store(true, Relaxed);
        self.loads.fetch_add(1, Relaxed);
        self.decoded.fetch_add(page.bytes, Relaxed);
        self.admit(page.bytes, id);
        page
    }

    /// Texture tile `index`, loading it if needed. A tile that fails to decode is recorded
    /// as the cache's error and served as zeros.
    pub fn tile(&self, index: u32) -> TileData {
        let slot = &self.tiles[index as usize];
        if let Some(t) = slot.data.read().expect("tile slot").as_ref() {
            if !slot.referenced.load(Relaxed) {
                slot.referenced.store(true, Relaxed);
            }
            return Arc::clone(t);
        }
        let data = Arc::new(match self.archive.read_tile(index) {
            Ok(d) => d,
            Err(e) => {
                self.record_error(&e);
                vec![0; canopy_format::TILE_BYTES as usize]
            }
        });
        {
            let mut w = slot.data.write().expect("tile slot");
            if let Some(t) = w.as_ref() {
                return Arc::clone(t);
            }
            *w = Some(Arc::clone(&data));
        }
        slot.referenced.store(true, Relaxed);
        self.tile_loads[self.tile_level[index as usize] as usize].fetch_add(1, Relaxed);
        let t = self.tile_resident.fetch_add(TILE_COST, Relaxed) + TILE_COST;
        self.tile_resident_peak.fetch_max(t, Relaxed);
        self.admit(TILE_COST, self.slots.len() as u32 + index);
        data
    }

    /// The first error met is kept; later ones are dropped.
    fn record_error(&self, e: &dyn std::fmt::Display) {
        self.error
            .lock()
            .expect("error lock")
            .get_or_insert_with(|| format!("{e:#}"));
    }

    /// Counts `bytes` just made resident in CLOCK slot `slot` (pages, then tiles; `u32::MAX`
    /// for state charged), evicting others while over budget.
    fn admit(&self, bytes: u64, slot: u32) {
        let now = self.resident.fetch_add(bytes, Relaxed) + bytes;
        if now > self.budget {
            self.evict(slot);
        }
        self.resident_peak
            .fetch_max(self.resident.load(Relaxed), Relaxed);
    }

    /// Takes back up to `bytes` of the lent share for the integrator's state (no more than
    /// is left of it), evicting pages while the cache is over its budget; returns the
    /// bytes taken.
    pub fn charge(&self, bytes: u64) -> u64 {
        let before = self
            .charged
            .fetch_update(Relaxed, Relaxed, |c| Some(c + bytes.min(self.lent - c)))
            .expect("the update always succeeds");
        let taken = bytes.min(self.lent - before);
        if taken > 0 {
            self.admit(taken, u32::MAX);
        }
        taken
    }

    /// Bytes the integrator's state has taken back of its lent share.
    pub fn charged(&self) -> u64 {
        self.charged.load(Relaxed)
    }

    /// Drops tile `i` if its reference bit is clear (clearing it otherwise).
    fn evict_tile(&self, i: usize) {
        let slot = &self.tiles[i];
        if slot.referenced.swap(false, Relaxed) {
            return;
        }
        if slot.data.write().expect("tile slot").take().is_some() {
            self.resident.fetch_sub(TILE_COST, Relaxed);
            self.tile_resident.fetch_sub(TILE_COST, Relaxed);
            self.tile_evictions.fetch_add(1, Relaxed);
        }
    }

    /// CLOCK sweep over pages and tiles (tiles numbered after the pages) until resident
    /// bytes fit the budget (at most two turns of the hand); `keep` is the slot just loaded.
    fn evict(&self, keep: u32) {
        let mut hand = self.hand.lock().expect("clock lock");
        let n = self.slots.len() + self.tiles.len();
        for _ in 0..2 * n {
            if self.resident.load(Relaxed) <= self.budget {
                break;
            }
            let i = *hand;
            *hand = (i + 1) % n;
            if i as u32 == keep {
                continue;
            }
            if i >= self.slots.len() {
                self.evict_tile(i - self.slots.len());
                continue;
            }
            let slot = &self.slots[i];
            if slot.pinned {
                continue;
            }
            if slot.referenced.swap(false, Relaxed) {
                continue;
            }
            if let Some(p) = slot.page.write().expect("slot").take() {
                self.resident.fetch_sub(p.bytes, Relaxed);
                let n = self.evictions.fetch_add(1, Relaxed) + 1;
                self.epoch.fetch_add(1, Relaxed);
                // Hand freed page memory back to the system now and then, so RSS follows
                // the cache rather than the high-water mark of a fragmented heap.
                #[cfg(target_os = "linux")]
                if n.is_multiple_of(TRIM_EVERY) {
                    // SAFETY: malloc_trim only releases free heap memory.
                    unsafe {
                        libc::malloc_trim(0);
                    }
                }
            }
        }
    }

    /// The first page error met, if any.
    pub fn error(&self) -> Option<String> {
        self.error.lock().expect("error lock").clone()
    }

    /// The page if it is resident, without loading it.
    pub fn get_resident(&self, id: u32) -> Option<Arc<Page>> {
        self.slots[id as usize].page.read().expect("slot").clone()
    }

    /// Moves whenever a page is evicted: handles taken before must be dropped.
    #[inline]
    pub fn epoch(&self) -> u64 {
        self.epoch.load(Relaxed)
    }

    /// Whether a traversal ever asked for the page.
    pub fn was_touched(&self, id: u32) -> bool {
        self.touched[id as usize].load(Relaxed)
    }

    pub fn resident_bytes(&self) -> u64 {
        self.resident.load(Relaxed)
    }

    /// Adds page lookups served without a load (counted by the tracers, off the hot path).
    pub fn add_lookups(&self, lookups: u64) {
        self.hits.fetch_add(lookups, Relaxed);
    }

    pub fn stats(&self) -> CacheStats {
        let misses = self.misses.load(Relaxed);
        let hits = self.hits.load(Relaxed).saturating_sub(misses);
        CacheStats {
            pages_loaded: self.loads.load(Relaxed),
            pages_evicted: self.evictions.load(Relaxed),
            hits,
            misses,
            bytes_decoded: self.decoded.load(Relaxed),
            resident_bytes_peak: self.resident_peak.load(Relaxed),
            pinned_bytes: self.pinned_bytes,
            pages_touched: self.touched.iter().filter(|t| t.load(Relaxed)).count() as u64,
            page_hit_rate: if hits + misses > 0 {
                hits as f64 / (hits + misses) as f64
            } else {
                1.0
            },
            texture_tiles_loaded: self.tile_loads.iter().map(|l| l.load(Relaxed)).sum(),
            texture_tiles_evicted: self.tile_evictions.load(Relaxed),
            texture_bytes_resident: self.tile_resident.load(Relaxed),
            texture_bytes_peak: self.tile_resident_peak.load(Relaxed),
            texture_tiles_loaded_per_level: {
                let mut v: Vec<u64> = self.tile_loads.iter().map(|l| l.load(Relaxed)).collect();
                while v.last() == Some(&0) {
                    v.pop();
                }
                v
            },
        }
    }

    /// Total decoded size of the whole archive (what an unlimited budget could reach).
    pub fn archive_decoded_bytes(&self) -> u64 {
        self.entries
            .iter()
            .map(|e| decoded_size(&self.archive, e))
            .sum()
    }

    /// The page holding global node `node` (pages number nodes consecutively in table
    /// order).
    pub fn page_of(&self, node: u64) -> Option<u32> {
        let i = self.entries.partition_point(|e| e.first_node <= node);
        let e = self.entries.get(i.checked_sub(1)?)?;
        (node < e.first_node + e.node_count as u64).then_some(i as u32 - 1)
    }

    pub fn root_page(&self) -> u32 {
        self.archive.header.root_page
    }
}

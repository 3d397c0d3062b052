//! The environment map's texels as square tiles of half floats, held whole or paged from a
//! temporary file under a byte budget (CLOCK, as the page cache pages texture tiles).
//!
//! Each tile is stored divided by its own power of two (`scale`), chosen so that its
//! brightest texel lies just under half's largest value: a sun of 10⁶ keeps its value and a
//! half-float input its every bit.

use glam::Vec3A as V;
use half::f16;
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering::Relaxed};
use std::sync::{Mutex, RwLock};

/// Texels along a tile's side.
pub const SIDE: usize = 64;
/// Texels in a tile.
pub const TEXELS: usize = SIDE * SIDE;
/// Bytes of a tile: RGB halves.
pub const TILE_BYTES: usize = TEXELS * 3 * 2;
/// Bytes a resident paged tile counts against the budget (texels and bookkeeping).
pub const TILE_COST: u64 = TILE_BYTES as u64 + 64;
/// Bytes every tile keeps beside its texels: its scale, and when paged its cache slot.
const SCALE_BYTES: u64 = 4;
const SLOT_BYTES: u64 = 24;
/// Bytes a paged map keeps per tile, resident or not.
pub const PAGED_TABLE_BYTES: u64 = SCALE_BYTES + SLOT_BYTES;

/// The power of two a tile whose brightest channel is `max` is stored divided by.
pub fn tile_scale(max: f32) -> f32 {
    match max > 0.0 && max.is_finite() {
        // 2^14 ≤ max / scale < 2^15, under half's largest finite value (65504).
        true => 2f32.powi(max.log2().floor() as i32 - 14),
        false => 1.0,
    }
}

/// Where the tiles live.
pub enum Store {
    /// Every tile, one after another.
    Whole(Vec<f16>),
    /// A file of tiles, `TILE_BYTES` each in order, read into a bounded cache.
    Paged(Paged),
}

pub struct Paged {
    file: File,
    slots: Vec<Slot>,
    /// Tiles that may be resident at once.
    capacity: u64,
    resident: AtomicU64,
    peak: AtomicU64,
    loads: AtomicU64,
    evictions: AtomicU64,
    hand: Mutex<usize>,
    error: Mutex<Option<String>>,
}

#[derive(Default)]
struct Slot {
    data: RwLock<Option<Box<[f16]>>>,
    referenced: AtomicBool,
}

impl Paged {
    pub fn new(file: File, tiles: usize, capacity: u64) -> Paged {
        Paged {
            file,
            slots: (0..tiles).map(|_| Slot::default()).collect(),
            capacity: capacity.max(1),
            resident: AtomicU64::new(0),
            peak: AtomicU64::new(0),
            loads: AtomicU64::new(0),
            evictions: AtomicU64::new(0),
            hand: Mutex::new(0),
            error: Mutex::new(None),
        }
    }

    /// Calls `f` with tile `t`'s texels, reading the tile if it is not resident. A tile the
    /// file cannot give is recorded as the error and read as black.
    fn with<R>(&self, t: usize, f: impl FnOnce(&[f16]) -> R) -> R {
        let slot = &self.slots[t];
        slot.referenced.store(true, Relaxed);
        if let Some(tile) = slot.data.read().expect("environment tile").as_deref() {
            return f(tile);
        }
        let tile = self.read(t);
        let r = f(&tile);
        let mut data = slot.data.write().expect("environment tile");
        if data.is_none() {
            *data = Some(tile);
            drop(data);
            self.loads.fetch_add(1, Relaxed);
            let now = self.resident.fetch_add(1, Relaxed) + 1;
            self.peak.fetch_max(now, Relaxed);
            if now > self.capacity {
                self.evict(t);
            }
        }
        r
    }

    fn read(&self, t: usize) -> Box<[f16]> {
        let mut bytes = vec![0u8; TILE_BYTES];
        if let Err(e) = self.file.read_exact_at(&mut bytes, (t * TILE_BYTES) as u64) {
            self.error
                .lock()
                .expect("environment error")
                .get_or_insert_with(|| format!("reading environment tile {t}: {e}"));
            bytes.fill(0);
        }
        bytes
            .chunks_exact(2)
            .map(|b| f16::from_le_bytes([b[0], b[1]]))
            .collect()
    }

    /// CLOCK: sweeps the slots, clearing reference bits and dropping tiles whose bit is
    /// clear, until the resident tiles fit; never drops tile `keep`.
    fn evict(&self, keep: usize) {
        let mut hand = self.hand.lock().expect("environment clock");
        let n = self.slots.len();
        for _ in 0..2 * n {
            if self.resident.load(Relaxed) <= self.capacity {
                return;
            }
            let i = *hand;
            *hand = (i + 1) % n;
            let slot = &self.slots[i];
            if i == keep || slot.referenced.swap(false, Relaxed) {
                continue;
            }
            if slot
                .data
                .write()
                .expect("environment tile")
                .take()
                .is_some()
            {
                self.resident.fetch_sub(1, Relaxed);
                self.evictions.fetch_add(1, Relaxed);
            }
        }
    }
}

/// Paging counters.
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct EnvStats {
    pub env_tiles_loaded: u64,
    pub env_tiles_evicted: u64,
    /// Bytes of the map resident at most (all of it when held whole).
    pub env_bytes_peak: u64,
}

/// The map's texels, `width` × `height`, in tiles row by row.
pub struct Tiles {
    pub width: usize,
    pub height: usize,
    /// Tiles across a row of tiles.
    across: usize,
    /// Per tile, the factor its stored halves are multiplied by.
    scale: Vec<f32>,
    store: Store,
}

impl Tiles {
    pub fn new(width: usize, height: usize, scale: Vec<f32>, store: Store) -> Tiles {
        Tiles {
            width,
            height,
            across: width.div_ceil(SIDE),
            scale,
            store,
        }
    }

    /// Tiles across and down a `width` × `height` map.
    pub fn count(width: usize, height: usize) -> usize {
        width.div_ceil(SIDE) * height.div_ceil(SIDE)
    }

    /// Texel (i, j), i < width, j < height.
    pub fn texel(&self, i: usize, j: usize) -> V {
        let t = (j / SIDE) * self.across + i / SIDE;
        let k = 3 * ((j % SIDE) * SIDE + i % SIDE);
        let rgb =
            |h: &[f16]| V::new(h[k].to_f32(), h[k + 1].to_f32(), h[k + 2].to_f32()) * self.scale[t];
        match &self.store {
            Store::Whole(all) => rgb(&all[t * 3 * TEXELS..(t + 1) * 3 * TEXELS]),
            Store::Paged(p) => p.with(t, rgb),
        }
    }

    /// Whether the texels are paged from a file.
    pub fn paged(&self) -> bool {
        matches!(self.store, Store::Paged(_))
    }

    /// Bytes of the per-tile tables, resident whatever is paged.
    fn table_bytes(&self) -> u64 {
        let per_tile = match &self.store {
            Store::Whole(_) => SCALE_BYTES,
            Store::Paged(_) => PAGED_TABLE_BYTES,
        };
        self.scale.len() as u64 * per_tile
    }

    /// Bytes the texels may hold resident.
    pub fn bytes_bound(&self) -> u64 {
        self.table_bytes()
            + match &self.store {
                Store::Whole(all) => (all.len() * 2) as u64,
                Store::Paged(p) => p.capacity * TILE_COST,
            }
    }

    pub fn stats(&self) -> EnvStats {
        match &self.store {
            Store::Whole(_) => EnvStats {
                env_bytes_peak: self.bytes_bound(),
                ..Default::default()
            },
            Store::Paged(p) => EnvStats {
                env_tiles_loaded: p.loads.load(Relaxed),
                env_tiles_evicted: p.evictions.load(Relaxed),
                env_bytes_peak: p.peak.load(Relaxed) * TILE_COST + self.table_bytes(),
            },
        }
    }

    /// The first tile the file could not give, if any.
    pub fn error(&self) -> Option<String> {
        match &self.store {
            Store::Whole(_) => None,
            Store::Paged(p) => p.error.lock().expect("environment error").clone(),
        }
    }
}

//! Integrators and the scene state they share.

pub mod cone;
pub mod path;

use crate::camera::Camera;
use crate::light::Lights;
use crate::material::Material;
use crate::paging::PageCache;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::Arc;

pub struct Scene {
    pub cache: Arc<PageCache>,
    pub materials: Vec<Material>,
    pub lights: Lights,
    pub camera: Camera,
    /// Longest path in segments (1: emitters seen directly); None for unbounded.
    pub max_depth: Option<u32>,
    /// One bit per node of the archive: leaves hit (ancestors are added at the end).
    pub touched: NodeSet,
    /// Pages whose stored light changed since the last pull (cone integrator).
    pub dirty: Vec<std::sync::atomic::AtomicBool>,
}

/// Per-thread counters, summed once per tile.
#[derive(Default, Clone, Copy)]
pub struct Counters {
    pub paths: u64,
}

/// A concurrent bit set over the archive's global node numbers.
pub struct NodeSet {
    bits: Vec<AtomicU64>,
}

impl NodeSet {
    pub fn new(nodes: u64) -> NodeSet {
        NodeSet {
            bits: (0..nodes.div_ceil(64)).map(|_| AtomicU64::new(0)).collect(),
        }
    }
    pub fn bytes(&self) -> u64 {
        self.bits.len() as u64 * 8
    }
    #[inline]
    pub fn insert(&self, i: u64) {
        let (w, b) = ((i / 64) as usize, 1u64 << (i % 64));
        if let Some(word) = self.bits.get(w) {
            if word.load(Relaxed) & b == 0 {
                word.fetch_or(b, Relaxed);
            }
        }
    }
    pub fn contains(&self, i: u64) -> bool {
        self.bits
            .get((i / 64) as usize)
            .is_some_and(|w| w.load(Relaxed) & (1 << (i % 64)) != 0)
    }
    pub fn count(&self) -> u64 {
        self.bits
            .iter()
            .map(|w| w.load(Relaxed).count_ones() as u64)
            .sum()
    }
}

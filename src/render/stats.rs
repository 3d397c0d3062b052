//! What a render reports: `--stats` JSON and the summary line.

use crate::integrator::{Kind, Scene, Stats};
use crate::paging::{deepest_first, CacheStats};
use anyhow::Result;
use rayon::prelude::*;
use std::collections::BTreeMap;

#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct Seconds {
    pub setup: f64,
    pub render: f64,
    /// Parts of `render` an integrator accounts for (the cone integrator's `pull` and
    /// `light`).
    #[serde(flatten)]
    pub parts: BTreeMap<&'static str, f64>,
    pub write: f64,
    pub total: f64,
}

#[derive(Clone, Debug, serde::Serialize)]
pub struct RenderStats {
    pub integrator: Kind,
    /// What made the image, as its EXR's attributes say it (`canopy assemble` checks that
    /// tiles agree): the archive's header checksum, the settings that decide pixels, and
    /// the seed.
    pub archive_checksum: String,
    pub settings: String,
    pub seed: u32,
    pub spp: u32,
    pub width: u32,
    pub height: u32,
    pub crop: Option<[u32; 4]>,
    pub threads: usize,
    pub seconds: Seconds,
    pub peak_rss_bytes: u64,
    pub mem_budget: Option<u64>,
    pub archive_decoded_bytes: u64,
    /// The page cache's counters; `resident_bytes_peak` adds the node statistics and the
    /// integrator's state.
    #[serde(flatten)]
    pub cache: CacheStats,
    /// The environment map's paging (`--env`), if it has one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub environment: Option<crate::light::env_tiles::EnvStats>,
    pub film_bytes: u64,
    /// With `--node-stats`: hit nodes and their ancestors (004 §5.2).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub unique_nodes_touched: Option<u64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub nodes_per_pixel: Option<f64>,
    pub rays: u64,
    pub paths: u64,
    /// Camera samples pixels took beyond one a pass (`--pixel-split`).
    pub further_samples: u64,
    pub rays_per_second: f64,
    pub paths_per_second: f64,
    pub emitters: u64,
    pub punctual_lights: u64,
    /// Which passes ran and why (the scene's features decide).
    pub passes: Vec<String>,
    /// Samples whose radiance was NaN or infinite (added as zero); 0 in a correct render.
    pub nonfinite_samples: u64,
    #[serde(flatten)]
    pub details: Stats,
    pub image_mean: [f64; 3],
    /// With a noise target: noise and used nodes at each power-of-two spp.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub growth: Vec<Checkpoint>,
}

/// A render's state after `spp` samples per pixel.
#[derive(Clone, Copy, Debug, serde::Serialize)]
pub struct Checkpoint {
    pub spp: u32,
    /// `Film::noise`: relative standard error of the image.
    pub noise: f64,
    /// Nodes hit and their ancestors so far (004 §5.2).
    pub unique_nodes: u64,
    /// Render time so far, the node counts included.
    pub seconds: f64,
}

impl std::fmt::Display for RenderStats {
    fn fmt(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        write!(
            f,
            "{}x{}, {} spp, {:.2} s ({:.2} M rays/s, {:.3} M paths/s), peak RSS {:.1} MiB, {} pages loaded, {} evicted, hit rate {:.4}",
            self.width,
            self.height,
            self.spp,
            self.seconds.render,
            self.rays_per_second / 1e6,
            self.paths_per_second / 1e6,
            self.peak_rss_bytes as f64 / 1048576.0,
            self.cache.pages_loaded,
            self.cache.pages_evicted,
            self.cache.page_hit_rate
        )
    }
}

/// Nodes touched = leaves hit plus all their ancestors (004 §5.2). Walks the pages that
/// were loaded, deepest first, marking a node when a child is marked. It reads only the
/// pages' node records (no traversal structures), the pages of one level in parallel.
pub fn ancestors_closure(scene: &Scene) -> Result<u64> {
    let archive = &scene.cache.archive;
    let entries = &scene.cache.entries;
    let pages = (0..archive.page_count())
        .filter(|&i| scene.cache.was_touched(i))
        .collect();
    for level in deepest_first(entries, pages) {
        level.par_iter().try_for_each(|&id| -> Result<()> {
            let nodes = archive.read_page(id)?.nodes;
            let first = entries[id as usize].first_node;
            let marked = |n: u64| scene.touched.contains(n);
            for (i, n) in nodes.iter().enumerate().rev() {
                let hit = if n.is_leaf() {
                    false
                } else if n.has_child_page() {
                    let f = entries[n.link[0] as usize].first_node;
                    marked(f) || marked(f + 1)
                } else {
                    marked(first + n.link[0] as u64) || marked(first + n.link[1] as u64)
                };
                if hit {
                    scene.touched.insert(first + i as u64);
                }
            }
            Ok(())
        })?;
    }
    Ok(scene.touched.count())
}

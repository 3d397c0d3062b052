//! What PBGI reports: its statistics and the lines that describe its passes.

use super::super::Stats;
use super::{wpbgi, PbgiIntegrator};
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};

/// What PBGI adds to the render's statistics.
#[derive(Clone, Debug, serde::Serialize)]
pub struct PbgiStats {
    pub pbgi_angle: f32,
    pub pbgi_resolution: usize,
    pub bake_seconds: f64,
    pub bake_samples: u64,
    /// Nodes splatted whole, and texels resolved by exact rays, over the render.
    pub splatted_nodes: u64,
    /// Texels filled by rasterized near leaves (the nearest hit of each texel's ray), and
    /// of them those shaded by a light sample rather than baked light.
    pub near_fragments: u64,
    pub exact_hits: u64,
    /// Pairs for direct light and rays for the glossy bounce that glossy receivers took
    /// beyond `--pbgi-glossy-rays` (`--pbgi-split`).
    pub split_pairs: u64,
    pub split_rays: u64,
    /// Exact rays where a rasterized leaf's cone found none of its triangles.
    pub gap_rays: u64,
    pub receiver_clusters: usize,
    pub clustered_receivers: u64,
    pub pbgi_reuse: u32,
    /// Receivers gathered at, and those that took their pixel's earlier gathers instead.
    pub gathers: u64,
    pub reused_gathers: u64,
    /// Pixels at an emitter's silhouette (these take `--edge-rays`).
    pub edge_pixels: u64,
    /// Texel rays traced exactly under `--pbgi-gather rays` (the default).
    pub traced_texels: u64,
    /// `--pbgi-cache`, its records, the gathers they average and the receivers that
    /// read them.
    pub irradiance_cache_error: f32,
    pub irradiance_records: u64,
    pub irradiance_record_gathers: u64,
    pub irradiance_cache_hits: u64,
    /// Receivers the cache covered but a surface nearer than its records' reach hid.
    pub irradiance_cache_rejects: u64,
    /// Pixels probed for the cache's error, and the records added where it was found.
    pub irradiance_cache_probes: u64,
    pub irradiance_probe_records: u64,
    /// WPBGI's glossy gathers (`--pbgi-glossy-bounce wavelet`), the adaptive micro-buffer's
    /// leaves over them (and the leaves the light importance split), the BRDF tables built
    /// and their kept Haar coefficients.
    pub wavelet_gathers: u64,
    pub amb_leaves: u64,
    pub amb_light_splits: u64,
    pub brdf_tables: usize,
    pub brdf_coefficients: usize,
    /// The radiance cache's records (`--pbgi-glossy-bounce cache`), the gathers they
    /// average and the receivers that read their glossy bounce from them.
    pub radiance_records: u64,
    pub radiance_gathers: u64,
    pub radiance_hits: u64,
}

/// What a render counts, over all threads.
#[derive(Default)]
pub(super) struct PbgiCounters {
    pub(super) splatted: AtomicU64,
    pub(super) near_fragments: AtomicU64,
    pub(super) exact_hits: AtomicU64,
    pub(super) split_pairs: AtomicU64,
    pub(super) split_rays: AtomicU64,
    pub(super) gap_rays: AtomicU64,
    /// Receivers gathered through a cluster's field.
    pub(super) clusters: AtomicU64,
    pub(super) gathers: AtomicU64,
    pub(super) reused: AtomicU64,
    pub(super) traced_texels: AtomicU64,
    pub(super) radiance_hits: AtomicU64,
    pub(super) cache_hits: AtomicU64,
    pub(super) cache_rejects: AtomicU64,
    pub(super) wavelet_gathers: AtomicU64,
    pub(super) amb_leaves: AtomicU64,
    pub(super) light_splits: AtomicU64,
}

impl PbgiIntegrator {
    pub(super) fn describe(&self) -> Vec<String> {
        let s = &self.settings;
        vec![
            match &s.bake_in {
                Some(path) => format!("bake: read from {} ({:.2} s)", path.display(), self.bake_s),
                None => format!(
                    "bake: {} bounce(s) of light reflected by every node, {} light samples per patch ({:.2} s)",
                    s.bake.bounces.map_or("all".to_string(), |n| n.to_string()),
                    s.bake.params(self.seed).samples,
                    self.bake_s
                ),
            },
            {
                let glossy = match (self.glossy_rays, self.split.most()) {
                    (1, _) => "glossy lobes: one exact ray".to_string(),
                    (k, n) if n > k => format!(
                        "glossy lobes: {k} exact rays, each paired with a light sample for direct light, {} split up to {n} per pixel by the spread of its earlier samples",
                        match self.split.splits_direct() {
                            true => "pairs and bounce rays",
                            false => "bounce rays",
                        }
                    ),
                    (k, _) => format!(
                        "glossy lobes: {k} exact rays, each paired with a light sample for direct light"
                    ),
                };
                let glossy = match s.glossy_bounce {
                    wpbgi::GlossyBounce::Wavelet | wpbgi::GlossyBounce::Cache => {
                        let (tables, coefs) = self.tables.sizes();
                        format!(
                            "{glossy}; the rough lobes' reflection by WPBGI (a dielectric's transmission by its lobe rays): {} gathers into adaptive micro-buffers of {:.0} leaves on average ({:.1} split by the light), the product with {tables} BRDF table(s) of {coefs} Haar coefficients",
                            self.tally.wavelet_gathers.load(Relaxed),
                            self.tally.amb_leaves.load(Relaxed) as f64
                                / self.tally.wavelet_gathers.load(Relaxed).max(1) as f64,
                            self.tally.light_splits.load(Relaxed) as f64
                                / self.tally.wavelet_gathers.load(Relaxed).max(1) as f64
                        )
                    }
                    wpbgi::GlossyBounce::Rays => glossy,
                };
                match s.rays() {
                    true => format!(
                        "pbgi: indirect light from a {}² hemicube micro-buffer for diffuse lobes, every texel's ray traced and reading the baked light ({glossy})",
                        s.resolution
                    ),
                    false => format!(
                        "pbgi: indirect light from a cut at {} texels' solid angle into a {}² hemicube micro-buffer for diffuse lobes ({glossy}); near leaves rasterized with baked patch light",
                        s.angle(), s.resolution
                    ),
                }
            },
            format!(
                "pbgi: each surface of a pixel (up to {} a pixel) gathers at every {}-th sample landing on it, the others reusing its gathers' irradiance",
                self.surfaces_per_pixel, s.reuse
            ),
            match &self.irradiance_cache {
                Some(c) => format!(
                    "pbgi: irradiance cache of error bound {}: {} records placed coarse to fine over the pixels ({} of them where one of {} probes disagreed with the cache), averaging {} gathers ({:.2} s), read by the receivers they cover",
                    s.cache, c.len(), self.probe_records, self.probed, c.gathers(), self.cache_s
                ),
                None => "pbgi: no irradiance cache".into(),
            },
            match &self.radiance_cache {
                Some(c) => format!(
                    "pbgi: radiance cache: {} records placed coarse to fine where one would cover its 8 neighbouring pixels, holding {} gathers of {} Haar coefficients each ({:.2} s), the glossy bounce of {} receivers; the others' from exact lobe rays",
                    c.records.len(),
                    c.records.gathers(),
                    c.coefficients(),
                    self.radiance_s,
                    self.tally.radiance_hits.load(Relaxed)
                ),
                None => "pbgi: no radiance cache".into(),
            },
            self.edge.describe(),
        ]
    }

    pub(super) fn pbgi_stats(&self) -> Stats {
        let (brdf_tables, brdf_coefficients) = self.tables.sizes();
        Stats::Pbgi(PbgiStats {
            pbgi_angle: self.settings.angle(),
            pbgi_resolution: self.settings.resolution,
            bake_seconds: self.bake_s,
            bake_samples: self.bake_samples,
            splatted_nodes: self.tally.splatted.load(Relaxed),
            near_fragments: self.tally.near_fragments.load(Relaxed),
            exact_hits: self.tally.exact_hits.load(Relaxed),
            split_pairs: self.tally.split_pairs.load(Relaxed),
            split_rays: self.tally.split_rays.load(Relaxed),
            gap_rays: self.tally.gap_rays.load(Relaxed),
            receiver_clusters: self.settings.clusters,
            clustered_receivers: self.tally.clusters.load(Relaxed),
            pbgi_reuse: self.settings.reuse,
            gathers: self.tally.gathers.load(Relaxed),
            traced_texels: self.tally.traced_texels.load(Relaxed),
            reused_gathers: self.tally.reused.load(Relaxed),
            edge_pixels: self.edge.pixels(),
            irradiance_cache_error: self.settings.cache,
            irradiance_records: self.irradiance_cache.as_ref().map_or(0, |c| c.len() as u64),
            irradiance_record_gathers: self.irradiance_cache.as_ref().map_or(0, |c| c.gathers()),
            irradiance_cache_hits: self.tally.cache_hits.load(Relaxed),
            irradiance_cache_rejects: self.tally.cache_rejects.load(Relaxed),
            irradiance_cache_probes: self.probed as u64,
            irradiance_probe_records: self.probe_records,
            wavelet_gathers: self.tally.wavelet_gathers.load(Relaxed),
            amb_leaves: self.tally.amb_leaves.load(Relaxed),
            amb_light_splits: self.tally.light_splits.load(Relaxed),
            brdf_tables,
            brdf_coefficients,
            radiance_records: self
                .radiance_cache
                .as_ref()
                .map_or(0, |c| c.records.len() as u64),
            radiance_gathers: self
                .radiance_cache
                .as_ref()
                .map_or(0, |c| c.records.gathers()),
            radiance_hits: self.tally.radiance_hits.load(Relaxed),
        })
    }
}

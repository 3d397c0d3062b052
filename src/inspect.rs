//! `canopy inspect`: what an archive holds and how compactly, and with `--verify` a full
//! check of every page.

use crate::progress;
use anyhow::Result;
use canopy_format::bake::BakeFile;
use canopy_format::{
    name_str, Archive, CameraRecord, EnvironmentRecord, Features, Node, PageReport,
};
use rayon::prelude::*;
use serde::Serialize;

#[derive(Debug, Serialize)]
pub struct Summary {
    pub path: String,
    pub version: String,
    pub node_bytes: usize,
    pub input_triangles: u64,
    pub triangles: u64,
    pub vertices: u64,
    pub nodes: u64,
    pub pages: u64,
    pub depth: u32,
    pub file_bytes: u64,
    pub decoded_bytes: u64,
    pub compression_ratio: f64,
    pub bytes_per_node_on_disk: f64,
    pub bytes_per_input_triangle: f64,
    pub mean_nodes_per_page: f64,
    pub mean_pages_per_path: f64,
    pub max_pages_per_path: u64,
    /// "triangle-weighted" from the page table, or "exact per leaf" after `--verify`.
    pub pages_per_path_method: &'static str,
    pub features: Vec<&'static str>,
    pub materials: Vec<String>,
    pub cameras: Vec<String>,
    pub lights: usize,
    /// The environment its scene file gave, if any.
    pub environment: Option<String>,
    /// What the converter said of the input: features the archive does not carry.
    pub notes: Vec<String>,
    /// Placements of prototypes, and the distinct prototypes they place.
    pub instances: usize,
    pub prototypes: usize,
    /// Textures (name and level-0 size), their tiles and the tiles' compressed bytes.
    pub textures: Vec<String>,
    pub texture_tiles: u32,
    pub texture_bytes: u64,
    pub bounds_min: [f32; 3],
    pub bounds_max: [f32; 3],
    pub verified: bool,
    /// The bake file given with `--bake`, checked against this archive.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub bake: Option<BakeSummary>,
}

#[derive(Debug, Serialize)]
pub struct BakeSummary {
    pub path: String,
    pub bounces: u32,
    pub samples_per_triangle: u32,
    pub seed: u32,
    pub file_bytes: u64,
    pub decoded_bytes: u64,
    pub record_bytes_per_node: u32,
    pub bytes_per_node_on_disk: f64,
    /// Glossy light's Haar coefficients (decoded bytes), over the file and per node;
    /// `wavelet_resolution` 0 when the bake stored none.
    pub coefficient_bytes: u64,
    pub coefficient_bytes_per_node: f64,
    pub wavelet_resolution: u32,
    pub wavelet_threshold: f32,
}

/// What a bake file holds; with `verify`, every block is decoded with its page and
/// checked as a render checks it (values, pyramids, coefficients and the kinds the tree
/// allows). With `budget`, a page and its block that one worker cannot hold within its
/// share of it are refused before they are read.
pub fn bake(a: &Archive, r: &BakeFile, verify: bool, budget: Option<u64>) -> Result<BakeSummary> {
    if verify {
        let entries = a.entries()?;
        let share = budget.map(|b| b / rayon::current_num_threads() as u64);
        (0..r.blocks.len() as u32)
            .into_par_iter()
            .try_for_each(|p| -> Result<()> {
                let bytes = crate::paging::decoded_size(a, &entries[p as usize])
                    + r.blocks[p as usize].raw_len as u64;
                if let Some(share) = share.filter(|&s| bytes > s) {
                    anyhow::bail!(
                        "{}: block {p} with its page takes {bytes} bytes decoded, more than a worker's share of --mem-budget ({share} bytes)",
                        r.path().display()
                    );
                }
                crate::paging::Page::decode(a, p)?.with_baked(r).map(drop)
            })?;
    }
    let h = &r.header;
    let nodes = h.nodes.max(1) as f64;
    Ok(BakeSummary {
        path: r.path().display().to_string(),
        bounces: h.bounces,
        samples_per_triangle: h.samples_per_triangle,
        seed: h.seed,
        file_bytes: h.file_len,
        decoded_bytes: r.blocks.iter().map(|b| b.raw_len as u64).sum(),
        record_bytes_per_node: h.record_size,
        bytes_per_node_on_disk: h.file_len as f64 / nodes,
        coefficient_bytes: h.coef_bytes,
        coefficient_bytes_per_node: h.coef_bytes as f64 / nodes,
        wavelet_resolution: h.wavelet_n,
        wavelet_threshold: h.wavelet_threshold,
    })
}

pub fn summarize(a: &Archive) -> Result<Summary> {
    let h = &a.header;
    let pages = a.entries()?;
    let file_bytes = std::fs::metadata(a.path()).map(|m| m.len()).unwrap_or(0);
    let compressed: u64 = pages.iter().map(|e| e.compressed_len as u64).sum();
    let decoded: u64 = pages.iter().map(|e| e.raw_len as u64).sum();
    let tri_paths: u64 = pages
        .iter()
        .map(|e| e.tri_count as u64 * (e.level as u64 + 1))
        .sum();
    Ok(Summary {
        path: a.path().display().to_string(),
        version: format!("{}.{}", h.version_major, h.version_minor),
        node_bytes: std::mem::size_of::<Node>(),
        input_triangles: h.input_triangles,
        triangles: h.triangles,
        vertices: h.vertices,
        nodes: h.nodes,
        pages: pages.len() as u64,
        depth: h.depth,
        file_bytes,
        decoded_bytes: decoded,
        compression_ratio: decoded as f64 / compressed.max(1) as f64,
        bytes_per_node_on_disk: file_bytes as f64 / h.nodes.max(1) as f64,
        bytes_per_input_triangle: file_bytes as f64 / h.input_triangles.max(1) as f64,
        mean_nodes_per_page: h.nodes as f64 / pages.len().max(1) as f64,
        mean_pages_per_path: tri_paths as f64 / h.triangles.max(1) as f64,
        max_pages_per_path: pages
            .iter()
            .filter(|e| e.tri_count > 0)
            .map(|e| e.level as u64 + 1)
            .max()
            .unwrap_or(0),
        pages_per_path_method: "triangle-weighted",
        features: Features::names(h.features),
        materials: a.materials.iter().map(|m| name_str(&m.name)).collect(),
        cameras: a
            .cameras
            .iter()
            .map(|c| {
                let view = match c.projection {
                    CameraRecord::ORTHOGRAPHIC => format!("orthographic, {} high", 2.0 * c.ymag),
                    _ => format!("{:.1}° high", c.yfov.to_degrees()),
                };
                format!("{} {}x{} ({view})", name_str(&c.name), c.width, c.height)
            })
            .collect(),
        lights: a.lights.len(),
        environment: a.environment.map(|e| match e.kind {
            EnvironmentRecord::SKY => format!(
                "sky, sun {}° up at azimuth {}°, turbidity {}",
                e.sun_elevation, e.sun_azimuth, e.turbidity
            ),
            _ => format!("map {}", e.path()),
        }),
        notes: a.notes.clone(),
        instances: a.header.instances.count as usize,
        // A prototype's root page is the one page besides the root page without a parent.
        prototypes: (0..pages.len() as u32)
            .filter(|&i| i != h.root_page && pages[i as usize].parent_page == canopy_format::NONE)
            .count(),
        textures: a
            .textures
            .iter()
            .map(|t| format!("{} {}x{}", name_str(&t.name), t.width, t.height))
            .collect(),
        texture_tiles: a.tile_count(),
        texture_bytes: a.tile_bytes(),
        bounds_min: h.bounds_min,
        bounds_max: h.bounds_max,
        verified: false,
        bake: None,
    })
}

/// Decodes and checks every page (in parallel), then the cross-page totals.
pub fn verify(a: &Archive, s: &mut Summary, show_progress: bool) -> Result<()> {
    let bar = progress::bar(show_progress, a.page_count() as u64, "verifying");
    let reports: Vec<PageReport> = (0..a.page_count())
        .into_par_iter()
        .map(|p| {
            let r = a.verify_page(p);
            bar.inc(1);
            r
        })
        .collect::<Result<_, _>>()?;
    bar.finish_and_clear();
    a.verify_totals(&reports)?;
    let leaves: u64 = reports.iter().map(|r| r.leaves).sum();
    s.mean_pages_per_path =
        reports.iter().map(|r| r.path_pages_sum).sum::<u64>() as f64 / leaves.max(1) as f64;
    s.pages_per_path_method = "exact per leaf";
    s.verified = true;
    Ok(())
}

/// Names joined by commas, or "none".
fn list_or_none(names: &[impl AsRef<str>]) -> String {
    if names.is_empty() {
        "none".into()
    } else {
        names
            .iter()
            .map(AsRef::as_ref)
            .collect::<Vec<_>>()
            .join(", ")
    }
}

impl std::fmt::Display for Summary {
    fn fmt(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        let s = self;
        let mib = |b: u64| b as f64 / (1 << 20) as f64;
        writeln!(f, "{}", s.path)?;
        writeln!(f, "  format version      {}", s.version)?;
        writeln!(f, "  node size           {} bytes", s.node_bytes)?;
        writeln!(f, "  input triangles     {}", s.input_triangles)?;
        writeln!(
            f,
            "  stored triangles    {} ({} vertices)",
            s.triangles, s.vertices
        )?;
        writeln!(f, "  nodes               {} (depth {})", s.nodes, s.depth)?;
        writeln!(
            f,
            "  pages               {} ({:.0} nodes per page)",
            s.pages, s.mean_nodes_per_page
        )?;
        writeln!(f,
        "  size on disk        {:.2} MiB ({:.1} bytes per node, {:.1} bytes per input triangle)",
        mib(s.file_bytes),
        s.bytes_per_node_on_disk,
        s.bytes_per_input_triangle
    )?;
        writeln!(
            f,
            "  decoded size        {:.2} MiB (compression ratio {:.2})",
            mib(s.decoded_bytes),
            s.compression_ratio
        )?;
        writeln!(
            f,
            "  pages per path      mean {:.2}, max {} ({})",
            s.mean_pages_per_path, s.max_pages_per_path, s.pages_per_path_method
        )?;
        writeln!(f, "  features            {}", list_or_none(&s.features))?;
        writeln!(
            f,
            "  materials           {}: {}",
            s.materials.len(),
            s.materials.join(", ")
        )?;
        writeln!(f, "  cameras             {}", list_or_none(&s.cameras))?;
        writeln!(f, "  punctual lights     {}", s.lights)?;
        if let Some(e) = &s.environment {
            writeln!(f, "  environment         {e}")?;
        }
        writeln!(
            f,
            "  textures            {}{}",
            s.textures.len(),
            if s.textures.is_empty() {
                String::new()
            } else {
                format!(
                    " in {} tiles, {:.2} MiB: {}",
                    s.texture_tiles,
                    s.texture_bytes as f64 / 1048576.0,
                    s.textures.join(", ")
                )
            }
        )?;
        if s.instances > 0 {
            writeln!(
                f,
                "  instances           {} of {} prototypes",
                s.instances, s.prototypes
            )?;
        }
        writeln!(
            f,
            "  bounds              {:?} .. {:?}",
            s.bounds_min, s.bounds_max
        )?;
        if !s.notes.is_empty() {
            writeln!(
                f,
                "  not carried         {} (what convert met and did instead):",
                s.notes.len()
            )?;
            for n in &s.notes {
                writeln!(f, "    {n}")?;
            }
        }
        if s.verified {
            writeln!(f, "  verify              ok: every page decodes, checksums match, links and bounds are consistent")?;
        }
        if let Some(r) = &s.bake {
            writeln!(f, "{}", r.path)?;
            writeln!(
                f,
                "  baked               {} bounce(s), {} light samples per triangle, seed {}",
                match r.bounces {
                    canopy_format::bake::ALL_BOUNCES => "all".to_string(),
                    n => n.to_string(),
                },
                r.samples_per_triangle,
                r.seed
            )?;
            writeln!(
                f,
                "  size on disk        {:.2} MiB ({:.1} bytes per node); decoded {:.2} MiB ({} bytes per node)",
                mib(r.file_bytes),
                r.bytes_per_node_on_disk,
                mib(r.decoded_bytes),
                r.record_bytes_per_node
            )?;
            if r.wavelet_resolution == 0 {
                writeln!(f, "  coefficients        none (no glossy light stored)")?;
            } else {
                writeln!(
                    f,
                    "  coefficients        {} bytes ({:.1} per node), cube maps of {}² texels a face, threshold {}",
                    r.coefficient_bytes,
                    r.coefficient_bytes_per_node,
                    r.wavelet_resolution,
                    r.wavelet_threshold
                )?;
            }
        }
        Ok(())
    }
}

use anyhow::Result;
use canopy::convert::{convert, BvhQuality, ConvertOptions, MissingTextures};
use canopy::units;
use clap::Args;
use std::path::PathBuf;

/// Convert meshes and scenes (glTF .gltf/.glb, PLY, OBJ) into a node archive.
///
/// Textures (glTF base colour, metallic-roughness and emission; OBJ map_Kd and map_Ke; PNG,
/// JPEG or TGA) are stored as tiled MIP pyramids beside the pages.
///
/// Several inputs merge into one scene. Memory stays under --mem-budget however large the
/// input: triangles are spilled to disk beside the output and built chunk by chunk.
#[derive(Args)]
pub struct ConvertArgs {
    /// Input files.
    #[arg(required = true)]
    inputs: Vec<PathBuf>,
    /// Output archive (.canopy). It appears only once complete.
    #[arg(short, long)]
    output: PathBuf,
    /// Memory the conversion may use, e.g. 512MiB, 2GiB, 1.5G: at least 98 MiB, whatever
    /// the number of triangles or instances.
    #[arg(long, default_value = "2GiB", value_parser = units::parse_size)]
    mem_budget: u64,
    /// TOML scene file: camera, materials and lights for meshes that carry none.
    #[arg(long)]
    scene: Option<PathBuf>,
    /// Most nodes in one page (treelet).
    #[arg(long, default_value_t = 512, value_parser = clap::value_parser!(u16).range(3..=4096))]
    page_nodes: u16,
    /// zstd compression level for pages (1 fast .. 19 small).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(i32).range(1..=22))]
    zstd_level: i32,
    /// Hierarchy build effort: `medium` (PLOC with more reinsertion, faster traversal),
    /// `fast` (about a fifth less build time), or `auto`: medium up to 8M triangles.
    #[arg(long, value_enum, default_value_t = BvhQuality::Auto)]
    bvh: BvhQuality,
    /// Store every placement of a glTF mesh as its own triangles. By default a mesh placed
    /// more than once (by several nodes or EXT_mesh_gpu_instancing) and emitting no light is
    /// stored once, with an instance per placement; the cone and PBGI integrators need
    /// flattened archives.
    #[arg(long)]
    flatten_instances: bool,
    /// A texture file that is not there: `error` (the default) stops the conversion naming
    /// it; `warn` prints a warning and its materials keep their factors alone.
    #[arg(long, value_enum, default_value_t = MissingTextures::Error)]
    missing_textures: MissingTextures,
    /// Also print the summary as JSON.
    #[arg(long)]
    json: bool,
}

pub fn run(a: ConvertArgs, progress: bool) -> Result<()> {
    let opts = ConvertOptions {
        inputs: a.inputs,
        output: a.output.clone(),
        mem_budget: a.mem_budget,
        scene: a.scene,
        page_nodes: a.page_nodes as usize,
        zstd_level: a.zstd_level,
        bvh: a.bvh,
        flatten_instances: a.flatten_instances,
        missing_textures: a.missing_textures,
        progress,
    };
    let r = convert(&opts)?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&r)?);
    } else {
        println!("{}: {r}", a.output.display());
    }
    Ok(())
}

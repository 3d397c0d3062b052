use anyhow::Result;
use canopy::convert::{
    convert, stages, BvhQuality, ConvertOptions, ConvertReport, MissingTextures,
};
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
///
/// On a cluster the chunks build as separate jobs (`tools/slurm/canopy-convert.sh`): `--work
/// DIR` with the inputs prepares, `--work DIR --chunk K` builds chunk K, `--work DIR --join`
/// writes the archive, the same bytes as one process writes.
#[derive(Args)]
pub struct ConvertArgs {
    /// Input files.
    #[arg(required_unless_present_any = ["chunk", "join"])]
    inputs: Vec<PathBuf>,
    /// Output archive (.canopy). It appears only once complete.
    #[arg(short, long, required_unless_present_any = ["chunk", "join"])]
    output: Option<PathBuf>,
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
    /// stored once, with an instance per placement.
    #[arg(long)]
    flatten_instances: bool,
    /// A texture file that is not there: `error` (the default) stops the conversion naming
    /// it; `warn` prints a warning and its materials keep their factors alone.
    #[arg(long, value_enum, default_value_t = MissingTextures::Error)]
    missing_textures: MissingTextures,
    /// Also print the summary as JSON.
    #[arg(long)]
    json: bool,
    /// Stage the conversion in DIR (shared storage) for separate chunk jobs: with inputs,
    /// prepare it and print the chunk count; with --chunk or --join, go on with it.
    #[arg(
        long,
        value_name = "DIR",
        help_heading = "Conversion in stages (cluster jobs)"
    )]
    work: Option<PathBuf>,
    /// Build chunk K (from 0) of the conversion prepared in --work.
    #[arg(long, value_name = "K", requires = "work", conflicts_with_all = ["join", "inputs", "output", "mem_budget", "scene", "page_nodes", "zstd_level", "bvh", "flatten_instances", "missing_textures"], help_heading = "Conversion in stages (cluster jobs)")]
    chunk: Option<u32>,
    /// Write the archive of the conversion in --work once every chunk is built, and remove
    /// the work files.
    #[arg(long, requires = "work", conflicts_with_all = ["inputs", "output", "mem_budget", "scene", "page_nodes", "zstd_level", "bvh", "flatten_instances", "missing_textures"], help_heading = "Conversion in stages (cluster jobs)")]
    join: bool,
}

pub fn run(a: ConvertArgs, progress: bool) -> Result<()> {
    if let (Some(work), Some(k)) = (&a.work, a.chunk) {
        let triangles = stages::chunk(work, k)?;
        println!("{}: chunk {k} built, {triangles} triangles", work.display());
        return Ok(());
    }
    if let (Some(work), true) = (&a.work, a.join) {
        let r = stages::join(work, progress)?;
        return report(&r, a.json);
    }
    let output = a
        .output
        .expect("clap requires --output without --chunk or --join");
    let opts = ConvertOptions {
        inputs: a.inputs,
        output: output.clone(),
        mem_budget: a.mem_budget,
        scene: a.scene,
        page_nodes: a.page_nodes as usize,
        zstd_level: a.zstd_level,
        bvh: a.bvh,
        flatten_instances: a.flatten_instances,
        missing_textures: a.missing_textures,
        progress,
    };
    if let Some(work) = &a.work {
        let r = stages::prepare(&opts, work)?;
        if a.json {
            println!("{}", serde_json::to_string_pretty(&r)?);
        }
        println!(
            "{}: prepared, {} chunk{} to build (--chunk 0 to {}), then --join",
            work.display(),
            r.chunks,
            if r.chunks == 1 { "" } else { "s" },
            r.chunks.saturating_sub(1)
        );
        return Ok(());
    }
    let r = convert(&opts)?;
    report(&r, a.json)
}

/// Prints a finished conversion's summary, as text or JSON.
fn report(r: &ConvertReport, json: bool) -> Result<()> {
    if json {
        println!("{}", serde_json::to_string_pretty(r)?);
    } else {
        let path = r.output.display();
        println!("{path}: {r}");
    }
    Ok(())
}

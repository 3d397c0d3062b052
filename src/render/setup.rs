//! From options to a scene ready to render: outputs checked, archive opened, camera and
//! window chosen, the memory budget split between pages and the integrator's state.

use super::defaults::{camera_note, chosen_environment, framing_camera, light_the_scene};
use super::RenderOptions;
use crate::camera::Camera;
use crate::image::{check_writable, same_file};
use crate::integrator::{NodeSet, Scene};
use crate::light::Environment;
use crate::light::LightSet;
use crate::light::Lights;
use crate::material::Material;
use crate::paging::PageCache;
use crate::texture::Textures;
use crate::trace::MAX_DEPTH;
use crate::units::format_size;
use anyhow::{bail, Context, Result};
use canopy_format::{Archive, CameraRecord};
use glam::Vec3A as V;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Largest image side accepted.
pub const MAX_SIDE: u32 = 32768;

pub struct Setup {
    pub exr: PathBuf,
    pub png: Option<PathBuf>,
    pub width: u32,
    pub height: u32,
    /// x0, x1, y0, y1 of the window rendered.
    pub window: [u32; 4],
    pub threads: usize,
    pub pool: rayon::ThreadPool,
    pub scene: Scene,
    /// The integrator's share of the memory budget.
    pub state_bytes: Option<u64>,
    /// Most camera samples a pass takes of a pixel (`--pixel-split`, or the integrator's
    /// default).
    pub pixel_split: u32,
    /// What the render took where the archive said nothing (a camera, light).
    pub notes: Vec<String>,
}

/// Where the EXR and (if asked) the PNG go: `-o x.png` writes x.png and x.exr beside it.
fn outputs(o: &RenderOptions) -> Result<(PathBuf, Option<PathBuf>)> {
    let images = image_outputs(&o.output, o.preview, (&o.archive, "the archive"))?;
    if let Some(stats) = &o.stats {
        not_over(stats, (&o.archive, "the archive"))?;
    }
    Ok(images)
}

/// Where an image written to `output` goes: `-o x.png` writes x.png and x.exr beside it,
/// `preview` a PNG beside an EXR. Each path is checked writable and not to be `input`
/// (named by the words given).
pub fn image_outputs(
    output: &Path,
    preview: bool,
    input: (&Path, &str),
) -> Result<(PathBuf, Option<PathBuf>)> {
    let ext = output
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    let (exr, png) = match ext.as_deref() {
        Some("exr") => (
            output.to_path_buf(),
            preview.then(|| output.with_extension("png")),
        ),
        Some("png") => (output.with_extension("exr"), Some(output.to_path_buf())),
        _ => bail!("{}: output must end in .exr or .png", output.display()),
    };
    for out in std::iter::once(&exr).chain(&png) {
        not_over(out, input)?;
    }
    Ok((exr, png))
}

/// Fails unless `out` can be written and is not `input` (named by the words given).
pub(super) fn not_over(out: &Path, (input, what): (&Path, &str)) -> Result<()> {
    if same_file(out, input) {
        bail!("{}: writing there would overwrite {what}", out.display());
    }
    check_writable(out)
}

/// The camera `--camera` names, or the first, or `default` where the archive has none.
fn camera<'a>(
    o: &RenderOptions,
    archive: &'a Archive,
    default: &'a CameraRecord,
) -> Result<&'a CameraRecord> {
    let name_of = |c: &CameraRecord| canopy_format::name_str(&c.name).to_string();
    match &o.camera {
        Some(name) => archive
            .cameras
            .iter()
            .find(|c| name_of(c) == *name)
            .with_context(|| {
                let names: Vec<_> = archive.cameras.iter().map(name_of).collect();
                format!(
                    "{}: no camera named {name:?} (cameras: {})",
                    o.archive.display(),
                    if names.is_empty() {
                        "none".into()
                    } else {
                        names.join(", ")
                    }
                )
            }),
        None => Ok(archive.cameras.first().unwrap_or(default)),
    }
}

fn resolution(o: &RenderOptions, cam: &CameraRecord) -> Result<(u32, u32)> {
    let (w, h) = match (o.width, o.height) {
        (Some(w), Some(h)) => (w, h),
        (Some(w), None) if cam.width > 0 => {
            (w, (w as u64 * cam.height as u64 / cam.width as u64) as u32)
        }
        (None, Some(h)) if cam.height > 0 => {
            ((h as u64 * cam.width as u64 / cam.height as u64) as u32, h)
        }
        (None, None) if cam.width > 0 && cam.height > 0 => (cam.width, cam.height),
        (w, h) => {
            let aspect = if cam.aspect > 0.0 { cam.aspect } else { 1.0 };
            match (w, h) {
                (Some(w), _) => (w, (w as f32 / aspect).round() as u32),
                (_, Some(h)) => ((h as f32 * aspect).round() as u32, h),
                _ => ((512.0 * aspect).round() as u32, 512),
            }
        }
    };
    if w == 0 || h == 0 || w > MAX_SIDE || h > MAX_SIDE {
        bail!("resolution {w}x{h} is out of range (each side 1..={MAX_SIDE})");
    }
    Ok((w, h))
}

fn window(o: &RenderOptions, width: u32, height: u32) -> Result<[u32; 4]> {
    match o.crop {
        Some([x0, x1, y0, y1]) => {
            if x0 >= x1 || y0 >= y1 || x1 > width || y1 > height {
                bail!(
                    "--crop {x0},{x1},{y0},{y1} is not a non-empty window inside {width}x{height}"
                );
            }
            Ok([x0, x1, y0, y1])
        }
        None => Ok([0, width, 0, height]),
    }
}

/// The archive with `--lights`' changes made to its lights.
fn open_lit(o: &RenderOptions) -> Result<Archive> {
    let mut archive = Archive::open(&o.archive)?;
    let Some(path) = &o.lights else {
        return Ok(archive);
    };
    if o.integrator.kind() != crate::integrator::Kind::Path {
        bail!(
            "--lights: only the path tracer renders a changed light set (the cone integrator and PBGI read lamps' light stored in the archive's nodes)"
        );
    }
    let set = LightSet::read(path)?;
    if set.environment_change().is_some() && o.env.is_some() {
        bail!(
            "{}: its [environment] changes the archive's environment, which --env or --sky replace (give their strength and rotation by flags instead)",
            path.display()
        );
    }
    set.apply(&mut archive)?;
    Ok(archive)
}

impl Setup {
    pub fn new(o: &RenderOptions) -> Result<Setup> {
        Setup::open(o, outputs(o)?)
    }

    /// The scene `o` names, for a render whose outputs are `exr` and `png` (checked by the
    /// caller).
    pub fn open(o: &RenderOptions, (exr, png): (PathBuf, Option<PathBuf>)) -> Result<Setup> {
        if o.spp == 0 {
            bail!("--spp must be at least 1");
        }
        let pixel_split = o.integrator.pixel_split(o.pixel_split)?;
        let archive = Arc::new(open_lit(o)?);
        let instances_note = o.integrator.check_archive(&archive)?;
        let framing = framing_camera(&archive);
        let cam = camera(o, &archive, &framing)?;
        let mut notes: Vec<String> = instances_note.into_iter().collect();
        if archive.cameras.is_empty() {
            notes.push(camera_note(o, cam));
        }
        let (width, height) = resolution(o, cam)?;
        let window = window(o, width, height)?;
        let threads = o.threads.unwrap_or_else(rayon::current_num_threads).max(1);
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .context("starting worker threads")?;
        let state_bytes = o.mem_budget.map(|b| o.integrator.state_share(b));
        // Under a budget, the map's share is kept aside with the state.
        let (env, env_note) = chosen_environment(o.env.as_ref(), &archive, o.mem_budget)?;
        notes.extend(env_note);
        let (kept, lent) = match o.integrator.lends_state() {
            true => (0, state_bytes.unwrap_or(0)),
            false => (state_bytes.unwrap_or(0), 0),
        };
        let aside = kept + env.as_ref().map_or(0, Environment::bytes);
        let camera = Camera::new(cam, width, height);
        let mut scene = open_scene(
            archive,
            camera,
            o.mem_budget.map(|total| Budget { total, aside, lent }),
            threads,
            o.max_depth,
        )?;
        let lights = std::mem::take(&mut scene.lights);
        let (lights, light_note) = light_the_scene(&o.archive, env, lights);
        scene.lights = lights;
        notes.extend(light_note);
        for note in &notes {
            eprintln!("note: {note}");
        }
        let spp = o.time.is_none().then_some(o.spp);
        scene.texture_scale = o.texture_filter.footprint_scale(spp);
        Ok(Setup {
            exr,
            png,
            width,
            height,
            window,
            threads,
            pool,
            scene,
            state_bytes,
            pixel_split,
            notes,
        })
    }
}

/// Working memory besides the pages and the integrator's state (code, stacks, film and I/O
/// buffers), at most: a budget keeps back the smaller of this and an eighth of itself, and
/// `SLACK_SHARE` of itself besides.
const RESERVE: u64 = 32 << 20;
/// The share of the budget kept back for what the allocator holds beyond live pages (freed
/// pages it keeps under eviction churn): 39 M instances under 4 GiB with the cache full
/// peaked 47 MiB past the budget plus film and 64 MiB without it, and 5 MiB short of it
/// with a 64th kept back.
const SLACK_SHARE: u64 = 32;
/// Per page: its table entry and cache slot.
const PER_PAGE: u64 = 128;
/// Per texture tile: its table entry, cache slot and level.
const PER_TILE: u64 = 72;

/// Per instance of an instance table (archives before 2.7, which is read whole; paged
/// records count with their pages): its record.
const PER_INSTANCE: u64 = std::mem::size_of::<canopy_format::InstanceRecord>() as u64;

/// What a budget of `b` bytes keeps back from the page cache for an archive of `pages`
/// pages, `tiles` texture tiles and `instances` instance-table records, all of which stay
/// in memory (without counting them, 200 M triangles at 1 GiB peaked at 1.27 GiB).
fn reserve(b: u64, pages: u64, tiles: u64, instances: u64) -> u64 {
    RESERVE.min(b / 8)
        + b / SLACK_SHARE
        + pages * PER_PAGE
        + tiles * PER_TILE
        + instances * PER_INSTANCE
}

/// The lamps of `archive`, emitting as `materials` say, and its punctual lights, in its
/// bounding sphere. Lamps are chosen by their mean radiance; a textured one's sample then
/// takes the texel at its point (`Textures::emission_ratio`).
pub fn gather_lights(
    archive: &Archive,
    materials: &[Material],
    textures: &Textures,
) -> Result<Lights> {
    let (lo, hi) = (
        V::from(archive.header.bounds_min),
        V::from(archive.header.bounds_max),
    );
    let mean: Vec<Material> = (0..materials.len() as u32)
        .map(|i| textures.mean_shade(&materials[i as usize], i))
        .collect();
    Lights::gather(
        archive,
        &mean,
        |m, c| textures.emission_corners(m, c),
        0.5 * (hi - lo).length(),
    )
}

/// How a memory budget is split for a scene's pages.
#[derive(Clone, Copy, Debug)]
pub struct Budget {
    pub total: u64,
    /// Bytes kept aside for the integrator's state and the environment map.
    pub aside: u64,
    /// Bytes the integrator's state takes back from the page cache as it grows
    /// (`PageCache::charge`); the pages may use them until then.
    pub lent: u64,
}

/// The scene an archive describes, its pages under `budget`.
pub fn open_scene(
    archive: Arc<Archive>,
    camera: Camera,
    budget: Option<Budget>,
    threads: usize,
    max_depth: Option<u32>,
) -> Result<Scene> {
    if archive.header.depth as usize > MAX_DEPTH {
        bail!(
            "{}: tree depth {} exceeds the {} this renderer traverses",
            archive.path().display(),
            archive.header.depth,
            MAX_DEPTH
        );
    }
    let touched = NodeSet::new(archive.header.nodes);
    // The page cache's budget, and how `--mem-budget` was split to give it (for errors).
    let lent = budget.map_or(0, |b| b.lent);
    let (budget, note) = match budget {
        Some(Budget {
            total: b,
            aside,
            lent,
        }) => {
            let state = aside + lent;
            let others = touched.bytes()
                + state
                + reserve(
                    b,
                    archive.page_count() as u64,
                    archive.tile_count() as u64,
                    archive.instances.len() as u64,
                );
            let pages = b.checked_sub(others).with_context(|| {
                format!(
                    "--mem-budget {} cannot hold the {} it keeps for the integrator's state and the environment map and the {} for node statistics and tables (pages, tiles, instances), and leave the page cache anything",
                    format_size(b),
                    format_size(state),
                    format_size(others - state)
                )
            })?;
            let lending = match lent {
                0 => String::new(),
                l => format!(
                    " and the state's {} until the state needs it",
                    format_size(l)
                ),
            };
            let note = format!(
                "--mem-budget {} keeps {} for the integrator's state and the environment map and {} for node statistics and tables (pages, tiles, instances), leaving the page cache {}{lending}",
                format_size(b),
                format_size(state),
                format_size(others - state),
                format_size(pages)
            );
            (Some(pages), Some(note))
        }
        None => (None, None),
    };
    let cache = PageCache::lending(Arc::clone(&archive), budget, lent, threads)
        .with_context(|| note.clone().unwrap_or_default())?;
    if let Some(note) = note {
        cache.note_budget(note);
    }
    let materials: Vec<Material> = archive
        .materials
        .iter()
        .map(Material::from_record)
        .collect();
    let textures = Textures::new(&archive.textures, &archive.materials);
    let lights = gather_lights(&archive, &materials, &textures)?;
    Ok(Scene {
        cache,
        materials,
        textures,
        texture_scale: 1.0,
        camera,
        lights,
        max_depth,
        touched,
    })
}

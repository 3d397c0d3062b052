//! Stage 1, import: every input streams its triangles into one spill file, checked record
//! by record, while the centroid bounds and the materials used are tracked.

use super::record_spill::{RecordWriter, Records};
use super::spill::{self, SpillWriter};
use super::{ConvertOptions, MatSummary};
use crate::import::{self, SceneDesc, SceneFile, SpillTri, TriangleSink};
use crate::progress;
use anyhow::{bail, Context, Result};
use canopy_format::validate::MAX_INSTANCES;
use canopy_format::{Features, NodeFlags};
use std::path::Path;

struct Spill {
    out: spill::Background,
    count: u64,
    lo: [f32; 3],
    hi: [f32; 3],
    materials_used: Vec<bool>,
    bar: indicatif::ProgressBar,
    /// Prototypes and instances; None when every placement is flattened.
    shared: Option<Shared>,
}

/// Meshes stored once: their triangles (object space) in one spill file, prototype after
/// prototype, and the placements, in another.
pub struct Shared {
    out: SpillWriter,
    pub prototypes: Vec<Prototype>,
    pub instances: RecordWriter<Placement>,
    open: Option<Prototype>,
}

/// One placement of a prototype, as the importer gave it.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub struct Placement {
    pub prototype: u32,
    /// Object-to-world, column-major 3×4 (an instance record's `to_world`).
    pub to_world: [f32; 12],
}

/// The prototypes' triangles, the prototypes, and the placements.
pub type SharedMeshes = (spill::Spill, Vec<Prototype>, Records<Placement>);

/// One prototype's triangles in the shared spill file.
#[derive(Clone, Copy)]
pub struct Prototype {
    pub start: u64,
    pub count: u64,
    /// Bounds of the triangles' centroids.
    pub lo: [f32; 3],
    pub hi: [f32; 3],
}

impl TriangleSink for Spill {
    fn push(&mut self, t: SpillTri) -> Result<()> {
        let m = t.material as usize;
        if m >= self.materials_used.len() {
            self.materials_used.resize(m + 1, false);
        }
        self.materials_used[m] = true;
        let (count, lo, hi) = match &mut self.shared {
            Some(Shared {
                out, open: Some(p), ..
            }) => {
                out.write(&t)?;
                (&mut p.count, &mut p.lo, &mut p.hi)
            }
            _ => {
                self.out.write(&t)?;
                (&mut self.count, &mut self.lo, &mut self.hi)
            }
        };
        for (a, c) in t.centroid().into_iter().enumerate() {
            lo[a] = lo[a].min(c);
            hi[a] = hi[a].max(c);
        }
        *count += 1;
        if count.is_multiple_of(65536) {
            self.bar.inc(65536);
        }
        Ok(())
    }

    fn shares_meshes(&self) -> bool {
        self.shared.is_some()
    }

    fn begin_prototype(&mut self) -> Result<()> {
        let s = self
            .shared
            .as_mut()
            .context("prototypes while flattening")?;
        s.open = Some(Prototype {
            start: s.out.position(),
            count: 0,
            lo: [f32::INFINITY; 3],
            hi: [f32::NEG_INFINITY; 3],
        });
        Ok(())
    }

    fn end_prototype(&mut self) -> Result<(u32, u64)> {
        let s = self
            .shared
            .as_mut()
            .context("prototypes while flattening")?;
        let p = s.open.take().context("no prototype was begun")?;
        s.prototypes.push(p);
        Ok((s.prototypes.len() as u32 - 1, p.count))
    }

    fn instance(&mut self, prototype: u32, to_world: [f32; 12]) -> Result<()> {
        let s = self.shared.as_mut().context("instances while flattening")?;
        if prototype as usize >= s.prototypes.len() || s.instances.len() >= MAX_INSTANCES as u64 {
            bail!(
                "instance {} of prototype {prototype}: out of range (at most {MAX_INSTANCES} instances)",
                s.instances.len()
            );
        }
        s.instances.push(&Placement {
            prototype,
            to_world,
        })
    }
}

/// Refuses an output path that names one of the inputs or the scene file.
fn refuse_overwriting_an_input(opts: &ConvertOptions) -> Result<()> {
    for input in opts.inputs.iter().chain(&opts.scene) {
        if crate::image::same_file(input, &opts.output) {
            bail!(
                "{}: the output would overwrite the input {}",
                opts.output.display(),
                input.display()
            );
        }
    }
    Ok(())
}

/// Imports every input into `spill`, checking the records each adds (and the scene file's)
/// as the archive reader will, so errors name the file they came from.
fn import_all(
    opts: &ConvertOptions,
    file: &SceneFile,
    scene: &mut SceneDesc,
    spill: &mut Spill,
) -> Result<()> {
    if let Some(p) = &opts.scene {
        scene
            .check_since([0; 3])
            .with_context(|| p.display().to_string())?;
    }
    for input in &opts.inputs {
        let before = scene.counts();
        import::import(input, scene, file, spill)?;
        scene
            .check_since(before)
            .with_context(|| input.display().to_string())?;
    }
    Ok(())
}

/// What the import stage hands on.
pub struct Imported {
    pub scene: SceneDesc,
    pub spill: spill::Spill,
    pub count: u64,
    /// Bounds of the triangles' centroids.
    pub lo: [f32; 3],
    pub hi: [f32; 3],
    materials_used: Vec<bool>,
    /// The prototypes' spill and the instances (None when flattening).
    pub shared: Option<SharedMeshes>,
}

/// Imports every input (and the scene file's records) into a spill file in `dir`.
pub fn import_inputs(opts: &ConvertOptions, file: &SceneFile, dir: &Path) -> Result<Imported> {
    refuse_overwriting_an_input(opts)?;
    let mut scene = SceneDesc {
        cameras: file.cameras(),
        lights: file.lights(),
        ..Default::default()
    };
    let mut spill = Spill {
        out: spill::Background::new(SpillWriter::create(dir, 1 << 20)?),
        count: 0,
        lo: [f32::INFINITY; 3],
        hi: [f32::NEG_INFINITY; 3],
        materials_used: Vec::new(),
        bar: progress::counter(opts.progress, "importing", "triangles"),
        shared: match opts.flatten_instances {
            true => None,
            false => Some(Shared {
                out: SpillWriter::create(dir, 256 << 10)?,
                prototypes: Vec::new(),
                instances: RecordWriter::create(dir)?,
                open: None,
            }),
        },
    };
    import_all(opts, file, &mut scene, &mut spill)?;
    spill.bar.finish_and_clear();
    let shared = match spill.shared {
        Some(s) if s.instances.len() > 0 => {
            Some((s.out.finish()?, s.prototypes, s.instances.finish()?))
        }
        _ => None,
    };
    Ok(Imported {
        scene,
        spill: spill.out.finish()?,
        count: spill.count,
        lo: spill.lo,
        hi: spill.hi,
        materials_used: spill.materials_used,
        shared,
    })
}

impl Imported {
    /// The archive's feature bits: from the materials triangles use and the scene's records.
    pub fn features(&self, mats: &[MatSummary]) -> u64 {
        let mut features = 0;
        for (m, _) in mats.iter().zip(&self.materials_used).filter(|(_, &u)| u) {
            for (flag, feature) in [
                (NodeFlags::EMISSIVE, Features::EMITTERS),
                (NodeFlags::GLOSSY, Features::GLOSSY),
                (NodeFlags::TRANSMISSIVE, Features::TRANSMISSIVE),
            ] {
                if m.flags & flag != 0 {
                    features |= feature;
                }
            }
        }
        for (has, feature) in [
            (self.scene.has_normals, Features::SHADING_NORMALS),
            (self.scene.textured, Features::TEXTURED_INPUT),
            (
                self.scene.has_uvs && !self.scene.textures.is_empty(),
                Features::TEXCOORDS,
            ),
            (
                self.scene.has_uvs2 && !self.scene.textures.is_empty(),
                Features::TEXCOORDS2 | Features::TEXCOORDS,
            ),
            (self.scene.has_colours, Features::COLOURS),
            (!self.scene.lights.is_empty(), Features::PUNCTUAL_LIGHTS),
            (self.shared.is_some(), Features::INSTANCES),
        ] {
            if has {
                features |= feature;
            }
        }
        features
    }
}

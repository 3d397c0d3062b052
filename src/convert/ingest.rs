//! Stage 1, import: every input streams its triangles into one spill file, checked record
//! by record, while the centroid bounds and the materials used are tracked.

use super::spill::{self, SpillWriter};
use super::{ConvertOptions, MatSummary};
use crate::import::{self, SceneDesc, SceneFile, SpillTri, TriangleSink};
use crate::progress;
use anyhow::{bail, Context, Result};
use canopy_format::{Features, NodeFlags};
use std::path::Path;

struct Spill {
    out: SpillWriter,
    count: u64,
    lo: [f32; 3],
    hi: [f32; 3],
    materials_used: Vec<bool>,
    bar: indicatif::ProgressBar,
}

impl TriangleSink for Spill {
    fn push(&mut self, t: SpillTri) -> Result<()> {
        for (a, c) in t.centroid().into_iter().enumerate() {
            self.lo[a] = self.lo[a].min(c);
            self.hi[a] = self.hi[a].max(c);
        }
        let m = t.material as usize;
        if m >= self.materials_used.len() {
            self.materials_used.resize(m + 1, false);
        }
        self.materials_used[m] = true;
        self.out.write(&t)?;
        self.count += 1;
        if self.count.is_multiple_of(65536) {
            self.bar.set_position(self.count);
        }
        Ok(())
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
        out: SpillWriter::create(dir, 1 << 20)?,
        count: 0,
        lo: [f32::INFINITY; 3],
        hi: [f32::NEG_INFINITY; 3],
        materials_used: Vec::new(),
        bar: progress::counter(opts.progress, "importing", "triangles"),
    };
    import_all(opts, file, &mut scene, &mut spill)?;
    spill.bar.finish_and_clear();
    Ok(Imported {
        scene,
        spill: spill.out.finish()?,
        count: spill.count,
        lo: spill.lo,
        hi: spill.hi,
        materials_used: spill.materials_used,
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
            (!self.scene.lights.is_empty(), Features::PUNCTUAL_LIGHTS),
        ] {
            if has {
                features |= feature;
            }
        }
        features
    }
}

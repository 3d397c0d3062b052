//! Importers: turn glTF, PLY and OBJ inputs into a stream of triangles plus the scene's
//! materials, cameras and lights. Triangles are pushed to a sink one by one so no importer
//! has to hold more than its input's vertex array.

mod gltf;
mod obj;
pub mod ply;
mod scene_file;

pub use scene_file::SceneFile;

use anyhow::{bail, Result};
use bytemuck::{Pod, Zeroable};
use canopy_format::codec::{oct_encode, NO_NORMAL};
use canopy_format::{CameraRecord, LightRecord, MaterialRecord};
use std::path::Path;

pub use canopy_format::codec::WHITE;

/// One input triangle as the importers produce it (spilled as 40 to 128 bytes, see
/// `convert::spill`).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct SpillTri {
    pub p: [[f32; 3]; 3],
    /// Octahedral shading normals; zero when the input had none.
    pub n: [u32; 3],
    pub material: u32,
    /// Mean curvature κ_s (004 eq. 4.23, edge-wise form), 0 without vertex normals.
    pub curvature: f32,
    /// Texture coordinates of the vertices (zero when the input had none).
    pub uv: [[f32; 2]; 3],
    /// The second set of texture coordinates its material reads (zero when none).
    pub uv2: [[f32; 2]; 3],
    /// Linear RGBA vertex colours, unorm16 (`WHITE` when the input had none).
    pub colour: [[u16; 4]; 3],
}

impl Default for SpillTri {
    fn default() -> Self {
        SpillTri {
            p: [[0.0; 3]; 3],
            n: [0; 3],
            material: 0,
            curvature: 0.0,
            uv: [[0.0; 2]; 3],
            uv2: [[0.0; 2]; 3],
            colour: [WHITE; 3],
        }
    }
}

/// A colour channel in [0, 1] (clamped; NaN reads 0) as linear unorm16.
pub fn unorm16(x: f32) -> u16 {
    (x.clamp(0.0, 1.0) * 65535.0).round() as u16
}

/// An sRGB-encoded channel in [0, 1] (8-bit colours of PLY and OBJ files) as linear unorm16.
pub fn srgb_unorm16(x: f32) -> u16 {
    unorm16(canopy_format::codec::srgb_decode(x.clamp(0.0, 1.0)))
}

impl SpillTri {
    pub fn centroid(&self) -> [f32; 3] {
        [0, 1, 2].map(|a| (self.p[0][a] + self.p[1][a] + self.p[2][a]) / 3.0)
    }
}

/// Receives the triangles an importer produces, and the instances of meshes it stores once.
pub trait TriangleSink {
    fn push(&mut self, t: SpillTri) -> Result<()>;
    /// Whether a mesh placed several times may be stored once, as a prototype with
    /// instances (false with `--flatten-instances`: every placement is pushed in world space).
    fn shares_meshes(&self) -> bool;
    /// Starts a prototype: the triangles pushed until `end_prototype` are in its object space.
    fn begin_prototype(&mut self) -> Result<()>;
    /// Ends the prototype; returns its number and how many triangles it holds.
    fn end_prototype(&mut self) -> Result<(u32, u64)>;
    /// Places prototype `prototype` with an object-to-world transform (column-major 3×4).
    fn instance(&mut self, prototype: u32, to_world: [f32; 12]) -> Result<()>;
}

/// Scene-level records collected from all inputs.
#[derive(Default)]
pub struct SceneDesc {
    pub materials: Vec<MaterialRecord>,
    pub cameras: Vec<CameraRecord>,
    pub lights: Vec<LightRecord>,
    pub has_normals: bool,
    pub textured: bool,
    /// Some triangle carries texture coordinates.
    pub has_uvs: bool,
    /// Some triangle carries a second set of texture coordinates.
    pub has_uvs2: bool,
    /// Some triangle carries vertex colours.
    pub has_colours: bool,
    /// The images materials name, in texture-table order.
    pub textures: Vec<TextureSource>,
    /// What the inputs hold that the archive does not carry, and what was done instead.
    pub notes: Vec<String>,
}

/// Most notes an archive records; one more then says how many were left out.
pub const MAX_NOTES: usize = 256;

impl TextureSource {
    /// The file, or the embedded image's name, for messages.
    pub fn describe(&self) -> String {
        match &self.file {
            Some(f) if self.bytes.is_none() => f.display().to_string(),
            _ => format!("'{}' (embedded)", self.name),
        }
    }
}

/// Where a texture's image comes from, and how it is read.
#[derive(Clone, Debug, PartialEq)]
pub struct TextureSource {
    /// A file, or bytes embedded in the input (named for messages by `name`).
    pub file: Option<std::path::PathBuf>,
    pub bytes: Option<std::sync::Arc<Vec<u8>>>,
    pub name: String,
    /// Colour data (base colour, emission): sRGB-encoded texels.
    pub srgb: bool,
    /// `TextureRecord` wrap modes of s and t.
    pub wrap: [u32; 2],
}

impl SceneDesc {
    /// Warns of something an input holds that the archive will not carry (naming what,
    /// where, and what was done instead), and records it for the archive's note table.
    pub fn note(&mut self, text: String) {
        eprintln!("warning: {text}");
        self.notes.push(text);
    }

    /// The notes as the archive stores them: the first `MAX_NOTES`, then how many more.
    pub fn note_records(&self) -> Vec<canopy_format::NoteRecord> {
        let mut out: Vec<_> = self
            .notes
            .iter()
            .take(MAX_NOTES)
            .map(|n| canopy_format::NoteRecord::new(n))
            .collect();
        if self.notes.len() > MAX_NOTES {
            let more = format!(
                "and {} more notes (convert prints them all)",
                self.notes.len() - MAX_NOTES
            );
            out.push(canopy_format::NoteRecord::new(&more));
        }
        out
    }

    /// How many materials, cameras and lights the scene holds, for `check_since`.
    pub fn counts(&self) -> [usize; 3] {
        [self.materials.len(), self.cameras.len(), self.lights.len()]
    }

    /// Refuses, among the records added since `counts` returned `from`, what the archive
    /// reader would refuse (NaN, infinities, values outside their glTF ranges), naming the
    /// record, so a conversion never writes an unreadable archive.
    pub fn check_since(&self, from: [usize; 3]) -> Result<()> {
        use canopy_format::validate::{check_camera, check_light, check_material};
        for m in &self.materials[from[0]..] {
            check_material(m).map_err(|e| {
                anyhow::anyhow!("material '{}': {e}", canopy_format::name_str(&m.name))
            })?;
        }
        for c in &self.cameras[from[1]..] {
            check_camera(c).map_err(|e| {
                anyhow::anyhow!("camera '{}': {e}", canopy_format::name_str(&c.name))
            })?;
        }
        for l in &self.lights[from[2]..] {
            check_light(l).map_err(|e| {
                anyhow::anyhow!("light '{}': {e}", canopy_format::name_str(&l.name))
            })?;
        }
        Ok(())
    }

    /// The index of texture `t` (added unless an equal one is there).
    pub fn add_texture(&mut self, t: TextureSource) -> Result<u16> {
        if let Some(i) = self.textures.iter().position(|x| *x == t) {
            return Ok(i as u16);
        }
        if self.textures.len() >= MaterialRecord::NO_TEXTURE as usize {
            bail!("more than {} textures", MaterialRecord::NO_TEXTURE);
        }
        self.textures.push(t);
        Ok(self.textures.len() as u16 - 1)
    }

    pub fn add_material(&mut self, m: MaterialRecord) -> Result<u32> {
        if self.materials.len() >= u16::MAX as usize {
            bail!("more than {} materials", u16::MAX);
        }
        self.materials.push(m);
        Ok(self.materials.len() as u32 - 1)
    }
}

/// A diffuse grey for meshes that carry no material and get none from the scene file.
pub fn default_material(name: &str) -> MaterialRecord {
    MaterialRecord {
        name: canopy_format::name_bytes(name),
        base_color: [0.8, 0.8, 0.8, 1.0],
        emission: [0.0; 3],
        metallic: 0.0,
        roughness: 1.0,
        ior: 1.5,
        transmission: 0.0,
        specular: 0.0,
        specular_color: [1.0; 3],
        flags: MaterialRecord::DOUBLE_SIDED,
        textures: [MaterialRecord::NO_TEXTURE; 4],
        alpha_cutoff: 0.5,
        normal_scale: 0.0,
        attenuation_color: [1.0; 3],
        attenuation_distance: 0.0,
        clearcoat: 0.0,
        clearcoat_roughness: 0.0,
        sheen_color: [0.0; 3],
        sheen_roughness: 0.0,
        layer_textures: [MaterialRecord::NO_TEXTURE; 4],
        coat_normal_texture: MaterialRecord::NO_TEXTURE,
        uv_streams: 0,
        coat_normal_scale: 0.0,
        uv_transforms: [MaterialRecord::IDENTITY_UV; MaterialRecord::SLOTS],
    }
}

/// Mean curvature of a triangle from its vertex normals. 004 eq. 4.23 divides by the edge's
/// projection on tangent axes, which is zero for edges along an axis; this uses the edge
/// itself as the direction: κ_e = ⟨n_i − n_j, p_i − p_j⟩ / |p_i − p_j|², averaged over the
/// three edges. Exactly 1/r on a sphere, like 4.23.
pub fn mean_curvature(p: &[[f32; 3]; 3], n: &[[f32; 3]; 3]) -> f32 {
    let mut sum = 0.0f64;
    let mut count = 0;
    for (i, j) in [(2, 1), (0, 2), (1, 0)] {
        let dp = [0, 1, 2].map(|a| p[i][a] as f64 - p[j][a] as f64);
        let dn = [0, 1, 2].map(|a| n[i][a] as f64 - n[j][a] as f64);
        let l2: f64 = dp.iter().map(|x| x * x).sum();
        if l2 > 0.0 {
            sum += (0..3).map(|a| dn[a] * dp[a]).sum::<f64>() / l2;
            count += 1;
        }
    }
    if count == 0 {
        0.0
    } else {
        (sum / count as f64) as f32
    }
}

/// Builds a spill record, validating the vertices. `what` names the triangle for errors.
pub fn make_tri(
    p: [[f32; 3]; 3],
    n: Option<[[f32; 3]; 3]>,
    material: u32,
    what: &dyn Fn() -> String,
) -> Result<SpillTri> {
    if p.iter().flatten().any(|x| !x.is_finite()) {
        bail!("{}: non-finite vertex coordinate {:?}", what(), p);
    }
    let (n_enc, curvature) = match n {
        Some(n) if n.iter().flatten().all(|x| x.is_finite()) => {
            (n.map(oct_encode), mean_curvature(&p, &n))
        }
        _ => ([NO_NORMAL; 3], 0.0),
    };
    Ok(SpillTri {
        p,
        n: n_enc,
        material,
        curvature,
        ..Default::default()
    })
}

/// Reads one input file into the sink, adding its materials, cameras and lights to `scene`.
pub fn import(
    path: &Path,
    scene: &mut SceneDesc,
    file: &SceneFile,
    sink: &mut dyn TriangleSink,
) -> Result<u64> {
    if !path.exists() {
        bail!("{}: no such file", path.display());
    }
    check_regular(path, u64::MAX, "input")?;
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(|e| e.to_ascii_lowercase())
        .unwrap_or_default();
    let n = match ext.as_str() {
        "gltf" | "glb" => gltf::import(path, scene, sink)?,
        "ply" => ply::import(path, scene, file, sink)?,
        "obj" => obj::import(path, scene, file, sink)?,
        _ => bail!(
            "{}: unknown input type '.{ext}' (expected .gltf, .glb, .ply or .obj)",
            path.display()
        ),
    };
    if n == 0 {
        bail!("{}: the mesh is empty (no triangles)", path.display());
    }
    Ok(n)
}

/// Material index for a raw mesh (PLY/OBJ without MTL): the scene file's choice or a default.
/// The material of a PLY or OBJ mesh without one of its own: the scene file's for `path`,
/// else `default`, or, for a mesh with vertex colours (`coloured`), white `vertex colour`
/// so the colours are the base colour.
fn raw_mesh_material(
    path: &Path,
    scene: &mut SceneDesc,
    file: &SceneFile,
    coloured: bool,
) -> Result<u32> {
    let m = file.material_for(path).unwrap_or_else(|| match coloured {
        true => MaterialRecord {
            base_color: [1.0; 4],
            ..default_material("vertex colour")
        },
        false => default_material("default"),
    });
    if let Some(i) = scene.materials.iter().position(|x| *x == m) {
        return Ok(i as u32);
    }
    scene.add_material(m)
}

/// A side file's metadata, refusing what is not a regular file (a directory, `/dev/zero`,
/// a FIFO) or is larger than `max` bytes, before anything is read.
pub(crate) fn check_regular(path: &Path, max: u64, what: &str) -> Result<std::fs::Metadata> {
    let m = std::fs::metadata(path).map_err(context(path))?;
    if !m.is_file() {
        bail!("{}: the {what} is not a regular file", path.display());
    }
    if m.len() > max {
        bail!(
            "{}: the {what} is {} bytes, more than the {max} accepted",
            path.display(),
            m.len()
        );
    }
    Ok(m)
}

/// Reads a whole side file after `check_regular`.
pub(crate) fn read_regular(path: &Path, max: u64, what: &str) -> Result<Vec<u8>> {
    check_regular(path, max, what)?;
    std::fs::read(path).map_err(context(path))
}

/// Longest text line the importers read (OBJ, MTL, PLY headers and ASCII bodies).
pub(crate) const MAX_LINE: usize = 1 << 20;

/// `read_line` that refuses a line longer than `MAX_LINE` instead of growing without bound
/// (a file without newlines would otherwise be read whole into one string).
pub(crate) fn read_line(
    r: &mut impl std::io::BufRead,
    line: &mut String,
) -> std::io::Result<usize> {
    use std::io::{BufRead, Read};
    line.clear();
    let n = r.by_ref().take(MAX_LINE as u64 + 1).read_line(line)?;
    if line.len() > MAX_LINE {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!("a line longer than {MAX_LINE} bytes"),
        ));
    }
    Ok(n)
}

/// Maps an I/O error to one that names the file.
pub(crate) fn context(path: &Path) -> impl Fn(std::io::Error) -> anyhow::Error + '_ {
    move |e| anyhow::anyhow!("{}: {e}", path.display())
}

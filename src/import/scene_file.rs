//! The small TOML scene file (`--scene FILE.toml`) that gives raw meshes a camera, materials
//! and lights:
//!
//! ```toml
//! [[camera]]
//! name = "main"
//! position = [0.0, 0.1, 0.4]
//! look_at = [0.0, 0.1, 0.0]
//! up = [0.0, 1.0, 0.0]      # default
//! yfov_degrees = 40.0       # default
//! width = 512               # default 512
//! height = 512              # default 512
//!
//! [[material]]
//! name = "default"          # "default" applies to every mesh that has no material
//! base_color = [0.8, 0.8, 0.8]
//! emission = [0.0, 0.0, 0.0]
//! metallic = 0.0
//! roughness = 1.0
//! double_sided = true      # default; false: the back neither reflects nor emits
//!
//! [assign]
//! "bunny.ply" = "default"   # input file name -> material name
//!
//! [[light]]
//! type = "point"            # point | spot | directional
//! position = [0.0, 1.0, 0.0]
//! color = [1.0, 1.0, 1.0]
//! intensity = 10.0
//! ```

use anyhow::{bail, Context, Result};
use canopy_format::{name_bytes, CameraRecord, LightRecord, MaterialRecord};
use glam::Vec3;
use serde::Deserialize;
use std::collections::HashMap;
use std::path::Path;

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneFile {
    #[serde(default)]
    camera: Vec<CameraDef>,
    #[serde(default)]
    material: Vec<MaterialDef>,
    #[serde(default)]
    assign: HashMap<String, String>,
    #[serde(default)]
    light: Vec<LightDef>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct CameraDef {
    name: Option<String>,
    position: [f32; 3],
    look_at: [f32; 3],
    #[serde(default = "up")]
    up: [f32; 3],
    #[serde(default = "yfov")]
    yfov_degrees: f32,
    #[serde(default = "res")]
    width: u32,
    #[serde(default = "res")]
    height: u32,
}

fn up() -> [f32; 3] {
    [0.0, 1.0, 0.0]
}
fn yfov() -> f32 {
    40.0
}
fn res() -> u32 {
    512
}
fn one() -> f32 {
    1.0
}
fn ior() -> f32 {
    1.5
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct MaterialDef {
    name: String,
    #[serde(default = "grey")]
    base_color: [f32; 3],
    #[serde(default)]
    emission: [f32; 3],
    #[serde(default)]
    metallic: f32,
    #[serde(default = "one")]
    roughness: f32,
    #[serde(default = "ior")]
    ior: f32,
    #[serde(default)]
    transmission: f32,
    #[serde(default)]
    specular: f32,
    #[serde(default = "yes")]
    double_sided: bool,
}

fn yes() -> bool {
    true
}
fn grey() -> [f32; 3] {
    [0.8; 3]
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct LightDef {
    name: Option<String>,
    #[serde(rename = "type")]
    kind: String,
    #[serde(default)]
    position: [f32; 3],
    #[serde(default = "down")]
    direction: [f32; 3],
    #[serde(default = "white")]
    color: [f32; 3],
    #[serde(default = "one")]
    intensity: f32,
    #[serde(default)]
    inner_cone_degrees: f32,
    #[serde(default = "outer")]
    outer_cone_degrees: f32,
}

fn down() -> [f32; 3] {
    [0.0, -1.0, 0.0]
}
fn white() -> [f32; 3] {
    [1.0; 3]
}
fn outer() -> f32 {
    45.0
}

impl SceneFile {
    pub fn load(path: &Path) -> Result<Self> {
        let bytes = super::read_regular(path, 16 << 20, "scene file")?;
        let text = String::from_utf8(bytes)
            .with_context(|| format!("{}: the scene file is not UTF-8", path.display()))?;
        let file: SceneFile =
            toml::from_str(&text).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
        for (input, m) in &file.assign {
            if !file.material.iter().any(|d| &d.name == m) {
                bail!("{}: [assign] gives '{input}' the material '{m}', which no [[material]] defines", path.display());
            }
        }
        for l in &file.light {
            if !["point", "spot", "directional"].contains(&l.kind.as_str()) {
                bail!(
                    "{}: light type '{}' (expected point, spot or directional)",
                    path.display(),
                    l.kind
                );
            }
        }
        Ok(file)
    }

    /// The material a raw mesh gets: its `[assign]` entry, else the one named "default".
    pub fn material_for(&self, input: &Path) -> Option<MaterialRecord> {
        let file = input.file_name()?.to_string_lossy();
        let name = self
            .assign
            .get(file.as_ref())
            .map(String::as_str)
            .unwrap_or("default");
        let d = self.material.iter().find(|d| d.name == name)?;
        let mut m = super::default_material(&d.name);
        m.name = name_bytes(&d.name);
        m.base_color = [d.base_color[0], d.base_color[1], d.base_color[2], 1.0];
        m.emission = d.emission;
        m.metallic = d.metallic;
        m.roughness = d.roughness;
        m.ior = d.ior;
        m.transmission = d.transmission;
        m.specular = d.specular;
        if !d.double_sided {
            m.flags &= !MaterialRecord::DOUBLE_SIDED;
        }
        Some(m)
    }

    pub fn cameras(&self) -> Vec<CameraRecord> {
        self.camera
            .iter()
            .enumerate()
            .map(|(i, c)| {
                let eye = Vec3::from(c.position);
                let z = (eye - Vec3::from(c.look_at)).normalize_or_zero();
                let x = Vec3::from(c.up).cross(z).normalize_or_zero();
                let y = z.cross(x);
                let mut to_world = [0.0; 12];
                for (k, v) in [x, y, z, eye].iter().enumerate() {
                    to_world[k * 3..k * 3 + 3].copy_from_slice(&v.to_array());
                }
                CameraRecord {
                    name: name_bytes(c.name.as_deref().unwrap_or(&format!("camera{i}"))),
                    to_world,
                    yfov: c.yfov_degrees.to_radians(),
                    aspect: c.width as f32 / c.height.max(1) as f32,
                    znear: 1e-3,
                    zfar: 0.0,
                    width: c.width,
                    height: c.height,
                    reserved: [0; 8],
                }
            })
            .collect()
    }

    pub fn lights(&self) -> Vec<LightRecord> {
        self.light
            .iter()
            .map(|l| LightRecord {
                name: name_bytes(l.name.as_deref().unwrap_or("")),
                kind: match l.kind.as_str() {
                    "spot" => LightRecord::SPOT,
                    "directional" => LightRecord::DIRECTIONAL,
                    _ => LightRecord::POINT,
                },
                color: l.color,
                intensity: l.intensity,
                position: l.position,
                direction: Vec3::from(l.direction).normalize_or_zero().to_array(),
                range: 0.0,
                inner_cone: l.inner_cone_degrees.to_radians(),
                outer_cone: l.outer_cone_degrees.to_radians(),
                reserved: [0; 8],
            })
            .collect()
    }
}

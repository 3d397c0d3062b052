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
//!
//! [environment]             # at most one: a map, or a sky (as render --env / --sky)
//! map = "sky.hdr"           # .exr or .hdr, relative to this file
//! strength = 1.0            # default
//! rotate_degrees = 0.0      # default
//! # sky = true, sun_elevation_degrees = 45.0, sun_azimuth_degrees = 135.0,
//! # turbidity = 3.0, ground_albedo = 0.3, sun_strength = 1.0 (the defaults)
//! ```

use anyhow::{bail, Context, Result};
use canopy_format::{name_bytes, CameraRecord, EnvironmentRecord, LightRecord, MaterialRecord};
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
    environment: Option<EnvironmentDef>,
    /// The file's directory, which relative paths start from.
    #[serde(skip)]
    dir: std::path::PathBuf,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct EnvironmentDef {
    map: Option<String>,
    #[serde(default)]
    sky: bool,
    #[serde(default = "one")]
    strength: f32,
    #[serde(default)]
    rotate_degrees: f32,
    #[serde(default = "elevation")]
    sun_elevation_degrees: f32,
    #[serde(default = "azimuth")]
    sun_azimuth_degrees: f32,
    #[serde(default = "turbidity")]
    turbidity: f32,
    #[serde(default = "albedo")]
    ground_albedo: f32,
    #[serde(default = "one")]
    sun_strength: f32,
}

fn elevation() -> f32 {
    45.0
}
fn azimuth() -> f32 {
    135.0
}
fn turbidity() -> f32 {
    3.0
}
fn albedo() -> f32 {
    0.3
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
        let mut file: SceneFile =
            toml::from_str(&text).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
        file.dir = path.parent().unwrap_or(Path::new("")).to_path_buf();
        for (input, m) in &file.assign {
            if !file.material.iter().any(|d| &d.name == m) {
                bail!("{}: [assign] gives '{input}' the material '{m}', which no [[material]] defines", path.display());
            }
        }
        file.check()
            .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
        Ok(file)
    }

    /// Every value a camera, material or light takes is one it can have: finite, in its
    /// range, with directions that are directions.
    fn check(&self) -> Result<()> {
        for (i, c) in self.camera.iter().enumerate() {
            let what = format!("camera {}", c.name.as_deref().unwrap_or(&i.to_string()));
            let (eye, at, up) = (
                Vec3::from(c.position),
                Vec3::from(c.look_at),
                Vec3::from(c.up),
            );
            if !(eye.is_finite() && at.is_finite() && up.is_finite()) {
                bail!("{what}: position, look_at and up must be finite");
            }
            let view = at - eye;
            if view.length() <= 0.0 {
                bail!("{what}: look_at is the position (no direction to look in)");
            }
            if up.cross(view).length() <= 1e-6 * up.length() * view.length() {
                bail!("{what}: up {:?} is zero or along the view direction", c.up);
            }
            if !(c.yfov_degrees > 0.0 && c.yfov_degrees < 180.0) {
                bail!(
                    "{what}: yfov_degrees {} (must be in (0, 180))",
                    c.yfov_degrees
                );
            }
            if !(1..=65_536).contains(&c.width) || !(1..=65_536).contains(&c.height) {
                bail!(
                    "{what}: {}x{} pixels (each side 1 to 65536)",
                    c.width,
                    c.height
                );
            }
        }
        for m in &self.material {
            let what = format!("material '{}'", m.name);
            let unit = [m.metallic, m.roughness, m.transmission, m.specular];
            if !m
                .base_color
                .iter()
                .chain(&unit)
                .all(|v| (0.0..=1.0).contains(v))
            {
                bail!("{what}: base_color, metallic, roughness, transmission and specular must be in [0, 1]");
            }
            if !m.emission.iter().all(|v| v.is_finite() && *v >= 0.0) {
                bail!("{what}: emission must be finite and ≥ 0");
            }
            if !(m.ior.is_finite() && m.ior >= 1.0) {
                bail!("{what}: ior {} (must be finite and ≥ 1)", m.ior);
            }
        }
        for (i, l) in self.light.iter().enumerate() {
            let what = format!("light {}", l.name.as_deref().unwrap_or(&i.to_string()));
            if !["point", "spot", "directional"].contains(&l.kind.as_str()) {
                bail!(
                    "{what}: type '{}' (expected point, spot or directional)",
                    l.kind
                );
            }
            let finite = Vec3::from(l.position).is_finite()
                && l.intensity.is_finite()
                && l.intensity >= 0.0
                && l.color.iter().all(|v| v.is_finite() && *v >= 0.0);
            if !finite {
                bail!(
                    "{what}: position, color and intensity must be finite, color and intensity ≥ 0"
                );
            }
            let dir = Vec3::from(l.direction);
            if l.kind != "point" && !(dir.is_finite() && dir.length() > 0.0) {
                bail!("{what}: direction {:?} is not a direction", l.direction);
            }
            if l.kind == "spot" {
                let (inner, outer) = (l.inner_cone_degrees, l.outer_cone_degrees);
                if !(outer > 0.0 && outer <= 90.0 && inner >= 0.0 && inner <= outer) {
                    bail!("{what}: cones inner {inner}° and outer {outer}° (need 0 ≤ inner ≤ outer, 0 < outer ≤ 90)");
                }
            }
        }
        Ok(())
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
                    projection: CameraRecord::PERSPECTIVE,
                    reserved: [0; 3],
                    ymag: 0.0,
                }
            })
            .collect()
    }

    /// The environment record: a map's path made absolute (it must be a regular file), or
    /// the sky's values checked as `render --sky` checks them.
    pub fn environment(&self) -> Result<Option<EnvironmentRecord>> {
        let Some(e) = &self.environment else {
            return Ok(None);
        };
        let mut rec = EnvironmentRecord {
            strength: e.strength,
            rotate_degrees: e.rotate_degrees,
            ..bytemuck::Zeroable::zeroed()
        };
        if !(e.strength.is_finite() && e.strength >= 0.0 && e.rotate_degrees.is_finite()) {
            bail!("[environment]: strength must be finite and ≥ 0 and rotate_degrees finite");
        }
        match (&e.map, e.sky) {
            (Some(map), false) => {
                let path = self.dir.join(map);
                let abs = std::fs::canonicalize(&path)
                    .with_context(|| format!("[environment] map {}", path.display()))?;
                if !abs.is_file() {
                    bail!("[environment] map {}: not a regular file", abs.display());
                }
                let s = abs.to_str().with_context(|| {
                    format!("[environment] map {}: the path is not UTF-8", abs.display())
                })?;
                if s.len() >= rec.path.len() {
                    bail!(
                        "[environment] map {s}: the path is {} bytes, more than an archive records ({}); give the map to render with --env",
                        s.len(),
                        rec.path.len() - 1
                    );
                }
                rec.kind = EnvironmentRecord::MAP;
                rec.path[..s.len()].copy_from_slice(s.as_bytes());
            }
            (None, true) => {
                let sky = crate::light::sky::SkyOptions {
                    elevation: e.sun_elevation_degrees,
                    azimuth: e.sun_azimuth_degrees,
                    turbidity: e.turbidity,
                    albedo: e.ground_albedo,
                    sun_strength: e.sun_strength,
                    place: None,
                };
                sky.resolved().context("[environment]")?;
                rec.kind = EnvironmentRecord::SKY;
                rec.sun_elevation = sky.elevation;
                rec.sun_azimuth = sky.azimuth;
                rec.turbidity = sky.turbidity;
                rec.ground_albedo = sky.albedo;
                rec.sun_strength = sky.sun_strength;
            }
            _ => bail!("[environment] gives either map = \"FILE\" or sky = true"),
        }
        Ok(Some(rec))
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

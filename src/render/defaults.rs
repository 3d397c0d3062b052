//! What a render takes where the archive says nothing: a camera that frames the scene, and
//! light for a scene that has none. Each default is named in a note (on stderr and in the
//! stats' `passes`), with the flag that changes it.

use super::RenderOptions;
use crate::light::sky::SkyOptions;
use crate::light::{Environment, Lights};
use anyhow::Result;
use canopy_format::{Archive, CameraRecord, EnvironmentRecord};
use glam::Vec3A as V;
use std::path::{Path, PathBuf};

/// Where the environment's light comes from.
#[derive(Clone, Debug)]
pub enum EnvSource {
    /// `--env`: an equirectangular map.
    Map(PathBuf),
    /// `--sky`: a clear sky and its sun.
    Sky(SkyOptions),
}

/// `--env` or `--sky`: the environment and how it is placed.
#[derive(Clone, Debug)]
pub struct EnvOptions {
    pub source: EnvSource,
    /// Factor on the map's radiance.
    pub strength: f32,
    /// Degrees about +Y.
    pub rotate: f32,
    /// Sample directions uniformly over the sphere rather than by the map's light.
    pub uniform_sampling: bool,
}

/// The default camera's vertical field of view: glTF viewers' 45°.
const FOV_DEG: f32 = 45.0;

/// The default camera's image: 640×480.
const SIZE: [u32; 2] = [640, 480];

/// glTF viewers' default view: from +Z toward the centre of the archive's bounds, far
/// enough that the bounding sphere fills the vertical field of view.
pub fn framing_camera(archive: &Archive) -> CameraRecord {
    let h = &archive.header;
    let (lo, hi) = (V::from(h.bounds_min), V::from(h.bounds_max));
    let centre = 0.5 * (lo + hi);
    let radius = (0.5 * (hi - lo).length()).max(1e-6);
    let fov = FOV_DEG.to_radians();
    let distance = radius / (0.5 * fov).sin();
    let pos = centre + V::Z * distance;
    let mut name = [0u8; 48];
    name[..7].copy_from_slice(b"default");
    CameraRecord {
        name,
        to_world: [
            1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, pos.x, pos.y, pos.z,
        ],
        yfov: fov,
        aspect: SIZE[0] as f32 / SIZE[1] as f32,
        znear: 0.0,
        zfar: 0.0,
        width: SIZE[0],
        height: SIZE[1],
        projection: CameraRecord::PERSPECTIVE,
        reserved: [0; 3],
        ymag: 0.0,
    }
}

/// The note saying the default camera was taken.
pub fn camera_note(o: &RenderOptions, cam: &CameraRecord) -> String {
    let p = &cam.to_world[9..12];
    format!(
        "{} has no camera: the default view looks down −Z from ({:.4}, {:.4}, {:.4}) at the centre of its bounds, which fill a {FOV_DEG}° field of view (give the input a camera, or a --scene file one)",
        o.archive.display(),
        p[0],
        p[1],
        p[2]
    )
}

/// The environment a render takes: the flags' (`--env`, `--sky`), else the one the archive
/// carries from its scene file, with a note naming it.
fn environment_options(
    flags: Option<&EnvOptions>,
    archive: &Archive,
) -> (Option<EnvOptions>, Option<String>) {
    let Some(e) = archive.environment else {
        return (flags.cloned(), None);
    };
    if let Some(f) = flags {
        let note = format!(
            "{}: the environment its scene file gave is replaced by the one the flags give",
            archive.path().display()
        );
        return (Some(f.clone()), Some(note));
    }
    let source = match e.kind {
        EnvironmentRecord::SKY => EnvSource::Sky(SkyOptions {
            elevation: e.sun_elevation,
            azimuth: e.sun_azimuth,
            turbidity: e.turbidity,
            albedo: e.ground_albedo,
            sun_strength: e.sun_strength,
            place: None,
        }),
        _ => {
            let dir = archive.path().parent().unwrap_or(Path::new(""));
            EnvSource::Map(dir.join(e.path()))
        }
    };
    let what = match &source {
        EnvSource::Map(p) => format!("the map {}", p.display()),
        EnvSource::Sky(s) => format!(
            "a sky with the sun {}° up at azimuth {}°",
            s.elevation, s.azimuth
        ),
    };
    let note = format!(
        "{}: lit by the environment its scene file gave, {what} (--env or --sky replace it)",
        archive.path().display()
    );
    let options = EnvOptions {
        source,
        strength: e.strength,
        rotate: e.rotate_degrees,
        uniform_sampling: false,
    };
    (Some(options), Some(note))
}

/// The environment a render or bake takes (`environment_options`), made and placed under
/// `budget`, and the note naming where it came from.
pub fn chosen_environment(
    flags: Option<&EnvOptions>,
    archive: &Archive,
    budget: Option<u64>,
) -> Result<(Option<Environment>, Option<String>)> {
    let (options, note) = environment_options(flags, archive);
    let env = options.map(|e| load_environment(&e, budget)).transpose()?;
    Ok((env, note))
}

/// `--env`'s map or `--sky`'s sky, made and placed; paged under its share of `budget` when
/// it does not fit.
fn load_environment(e: &EnvOptions, budget: Option<u64>) -> Result<Environment> {
    let share = budget.map(Environment::share);
    match &e.source {
        EnvSource::Map(path) => {
            Environment::from_file(path, e.strength, e.rotate, e.uniform_sampling, share)
        }
        EnvSource::Sky(sky) => Environment::sky(sky, e.strength, e.rotate, share),
    }
}

/// The archive's lights with `env`; with neither emitters nor `env`, a uniform white
/// environment (radiance 1), named in the note returned.
pub fn light_the_scene(
    archive: &Path,
    env: Option<Environment>,
    lights: Lights,
) -> (Lights, Option<String>) {
    if let Some(env) = env {
        return (lights.with_environment(env), None);
    }
    if !lights.is_empty() {
        return (lights, None);
    }
    let note = format!(
        "{} has no light source: a uniform white environment (radiance 1) lights it (--env FILE lights it with a map, --sky with a sky and sun)",
        archive.display()
    );
    let sky = Environment::uniform(V::ONE);
    (lights.with_environment(sky), Some(note))
}

//! What a glTF scene says of its view and light: the perspective camera, the render size
//! and KHR_lights_punctual.

use canopy_format::{name_bytes, CameraRecord, LightRecord};
use glam::{Mat4, Vec3};

/// The render resolution the bundled scenes carry in top-level `extras.render`.
pub(super) fn render_size(doc: &gltf::Document) -> (u32, u32) {
    let extras = doc
        .as_json()
        .extras
        .as_ref()
        .and_then(|e| serde_json::from_str::<serde_json::Value>(e.get()).ok());
    let get = |k: &str| {
        extras
            .as_ref()
            .and_then(|e| e["render"][k].as_u64())
            .map(|v| v as u32)
            .unwrap_or(0)
    };
    (get("width"), get("height"))
}

/// The camera's record, None for an orthographic one whose magnification is zero or not
/// finite (it shows nothing).
pub(super) fn camera(
    cam: &gltf::Camera,
    node: &gltf::Node,
    world: Mat4,
    width: u32,
    height: u32,
) -> Option<CameraRecord> {
    let c = world.to_cols_array();
    let mut to_world = [0.0f32; 12];
    for col in 0..4 {
        to_world[col * 3..col * 3 + 3].copy_from_slice(&c[col * 4..col * 4 + 3]);
    }
    let name = node
        .name()
        .or(cam.name())
        .map(str::to_string)
        .unwrap_or_else(|| format!("camera{}", cam.index()));
    let base = CameraRecord {
        name: name_bytes(&name),
        to_world,
        width,
        height,
        ..bytemuck::Zeroable::zeroed()
    };
    match cam.projection() {
        gltf::camera::Projection::Perspective(p) => Some(CameraRecord {
            yfov: p.yfov(),
            aspect: p.aspect_ratio().unwrap_or(0.0),
            znear: p.znear(),
            zfar: p.zfar().unwrap_or(0.0),
            ..base
        }),
        // glTF's xmag and ymag are half the view's width and height.
        gltf::camera::Projection::Orthographic(o) => {
            let (x, y) = (o.xmag().abs(), o.ymag().abs());
            (x > 0.0 && y > 0.0 && (x / y).is_finite() && y.is_finite()).then(|| CameraRecord {
                projection: CameraRecord::ORTHOGRAPHIC,
                ymag: y,
                aspect: x / y,
                znear: o.znear().max(0.0),
                zfar: o.zfar().max(0.0),
                ..base
            })
        }
    }
}

pub(super) fn punctual(l: &gltf::khr_lights_punctual::Light, world: Mat4) -> LightRecord {
    use gltf::khr_lights_punctual::Kind;
    let (kind, inner, outer) = match l.kind() {
        Kind::Point => (LightRecord::POINT, 0.0, 0.0),
        Kind::Spot {
            inner_cone_angle,
            outer_cone_angle,
        } => (LightRecord::SPOT, inner_cone_angle, outer_cone_angle),
        Kind::Directional => (LightRecord::DIRECTIONAL, 0.0, 0.0),
    };
    LightRecord {
        name: name_bytes(l.name().unwrap_or("")),
        kind,
        color: l.color(),
        intensity: l.intensity(),
        position: world.transform_point3(Vec3::ZERO).to_array(),
        direction: world
            .transform_vector3(Vec3::NEG_Z)
            .normalize_or_zero()
            .to_array(),
        range: l.range().unwrap_or(0.0),
        inner_cone: inner,
        outer_cone: outer,
        reserved: [0; 8],
    }
}

//! Where a ray scatters, once for every integrator: the first surface it does not pass
//! through (alpha holes, stochastically), and that hit prepared for shading (its side,
//! frame, BSDF and emission).

use super::Scene;
use crate::material::{Bsdf, Frame};
use crate::texture::Shaded;
use crate::trace::{offset_origin, Hit, Ray, Tracer};
use glam::Vec3A as V;

/// Most alpha holes one path segment or shadow ray passes through.
pub const MAX_PASSES: u32 = 64;

/// Stochastic opacity: whether a ray goes on through a surface of `opacity` (a hole under
/// an alpha mask; with probability 1 − alpha under blend), from the sample number `u` moved
/// along a golden-ratio sequence for the `passes` already made on this segment.
pub fn passes_through(opacity: f32, u: f32, passes: u32) -> bool {
    opacity < 1.0 && (u + passes as f32 * 0.618_034).fract() >= opacity
}

/// A number in [0, 1) for `passes_through` on a ray that draws no sample of its own for
/// it (PBGI's gather, lobe and edge rays): its direction's bits hashed, so rays apart
/// decide apart.
pub fn hole_number(d: V) -> f32 {
    let [x, y, z] = d.to_array().map(f32::to_bits);
    let mut h = (x as u64) << 32 ^ (y as u64) << 16 ^ z as u64 ^ 0x9E37_79B9_7F4A_7C15;
    h = (h ^ (h >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    h = (h ^ (h >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    (h >> 40) as f32 / (1u64 << 24) as f32
}

/// A surface a ray scatters at: the hit, its unit geometric normal and area, and the
/// distance the ray travelled through holes before it.
pub struct Scatter {
    pub hit: Hit,
    pub ng: V,
    pub area: f32,
    pub travelled: f32,
}

impl Scatter {
    /// The distance `ray` (the ray that found the hit) ran to reach it, holes included.
    pub fn length(&self, ray: &Ray) -> f32 {
        self.travelled + self.hit.t * ray.d.length()
    }

    /// The hit prepared for shading as `ray` sees it, its material looked up at the camera's
    /// footprint (`Scene::material_at_hit`).
    pub fn shading(&self, scene: &Scene, ray: &Ray) -> ShadingPoint {
        let wo = -ray.d.normalize();
        let shaded = scene.material_at_hit(&self.hit, ray.d);
        ShadingPoint::new(&self.hit, self.ng, wo, &shaded)
    }
}

/// Why a ray scatters nowhere.
#[derive(Debug, PartialEq)]
pub enum Missed {
    /// It left the scene.
    Left,
    /// It met a triangle of no area.
    Degenerate,
}

/// The first surface `ray` scatters at: holes (alpha below the cutoff, or a blend's
/// transparency) are passed by `passes_through` with the sample number `u`, counting in
/// `passes` (at most `MAX_PASSES` on a path), each moving `ray`'s origin past the hole.
/// Otherwise why not: the ray left the scene (toward the environment, along `ray`), or it
/// met a degenerate triangle. Every hit met is touched (`Scene::touch`).
pub fn scattering_hit(
    scene: &Scene,
    tr: &mut Tracer,
    ray: &mut Ray,
    u: f32,
    passes: &mut u32,
) -> Result<Scatter, Missed> {
    let mut travelled = 0.0f32;
    loop {
        let hit = tr.closest_hit(ray).ok_or(Missed::Left)?;
        scene.touch(&hit);
        let ng_raw = hit.ng();
        let area = 0.5 * ng_raw.length();
        if area.is_nan() || area <= 0.0 {
            return Err(Missed::Degenerate);
        }
        let ng = ng_raw / (2.0 * area);
        if *passes < MAX_PASSES && passes_through(scene.opacity_at(&hit), u, *passes) {
            *passes += 1;
            travelled += hit.t * ray.d.length();
            let (p, err) = hit.point();
            ray.o = offset_origin(p, err, ng, ray.d);
            continue;
        }
        return Ok(Scatter {
            hit,
            ng,
            area,
            travelled,
        });
    }
}

/// A hit prepared for shading, seen from `wo` (unit, toward the viewer): the side it is
/// seen from, the shading frame (normal maps applied), the BSDF of that side and `wo` in
/// its frame.
#[derive(Clone, Copy)]
pub struct ShadingPoint {
    pub p: V,
    pub err: V,
    /// Unit geometric normal (winding side), and turned to the side seen.
    pub ng: V,
    pub n: V,
    pub front: bool,
    pub frame: Frame,
    pub bsdf: Bsdf,
    pub wo_l: V,
    pub emitted: V,
    pub absorbs: bool,
    /// The volume's attenuation coefficient where the hit is on a back face (the ray ran
    /// inside the mesh), zero otherwise: see `through`.
    pub sigma: V,
}

impl ShadingPoint {
    /// `shaded`: the hit's material as looked up (its texture footprint is the caller's).
    pub fn new(hit: &Hit, ng: V, wo: V, shaded: &Shaded) -> ShadingPoint {
        let m = &shaded.m;
        let front = ng.dot(wo) > 0.0;
        let (p, err) = hit.point();
        let frame = Frame::new(shading_normal(ng, front, shaded.normal));
        let mut bsdf = m.bsdf(front);
        // A coat normal tilted past the base's shading normal's horizon is not used.
        if let Some(c) = shaded.coat_normal {
            let cn = frame.to_local(shading_normal(ng, front, Some(c)));
            if cn.z > 0.0 {
                bsdf.coat_n = cn;
            }
        }
        ShadingPoint {
            p,
            err,
            ng,
            n: if front { ng } else { -ng },
            front,
            frame,
            bsdf,
            wo_l: frame.to_local(wo),
            emitted: m.emitted(front),
            absorbs: m.absorbs(front),
            sigma: if front { V::ZERO } else { m.sigma },
        }
    }

    /// The share of light that survives the `length` the ray ran to reach this point: less
    /// than 1 only inside a mesh with a volume (`Material::transmittance`).
    pub fn through(&self, length: f32) -> V {
        (-self.sigma * length).exp()
    }
}

pub fn on_side(frame: &Frame, n: V, w: V) -> bool {
    frame.n.dot(w) * n.dot(w) > 0.0
}

/// The shading normal at a triangle hit with unit geometric normal `ng`, on the side
/// `front` says: the normal texture's `bumped` normal (`Shaded::normal`), or the side's
/// geometric normal. Seen from the back, the bumped normal is turned round whole, as a
/// real bump seen from behind is a dent.
pub fn shading_normal(ng: V, front: bool, bumped: Option<V>) -> V {
    let n = bumped.unwrap_or(ng);
    if front {
        n
    } else {
        -n
    }
}

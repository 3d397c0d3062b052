//! Shading a hit for PBGI: the surface's frame and BSDF, its direct light (a light sample
//! weighed by MIS against a ray sampled from its rough specular lobes, as the path tracer
//! does), and what a hit the gather sees sends back (baked patch light, else direct light).

use super::patch;
use crate::integrator::direct::{emission_weight, escaped_light};
use crate::integrator::surface::{hole_number, scattering_hit, Missed};
use crate::integrator::{
    bsdf_term, mis_weight, on_side, sample_light_weighted, Receiver, Scene, ShadingPoint,
};
use crate::material::Bsdf;
use crate::paging::{Corners, WHITE};
use crate::paging::{NodeRef, Page};
use crate::trace::{offset_origin, Cone, Hit, Ray, Tracer, NO_INSTANCE};
use glam::Vec3A as V;

/// What a hit sends back along `w`: the baked light of the finest patch under it, or,
/// where the bake holds nothing (back faces, non-diffuse surfaces, instanced meshes, whose
/// light depends on the placement), direct light as the
/// path tracer would take it, with the numbers `u` gives (drawn only then: most hits read
/// the bake); the flag says it was sampled.
pub(super) fn hit_light(
    scene: &Scene,
    tr: &mut Tracer,
    page: &Page,
    hit: &Hit,
    w: V,
    u: impl FnOnce() -> [f32; 6],
) -> (V, bool) {
    let t = page
        .bvh
        .get(hit.leaf.wrapping_sub(page.first_node) as usize)
        .filter(|_| hit.instance == NO_INSTANCE)
        .and_then(|n| match n.link() {
            NodeRef::Leaf { first, .. } => Some((first + hit.slot) as usize),
            _ => None,
        });
    let front = hit.ng().dot(w) < 0.0;
    if let Some(l) = t.and_then(|t| baked_light(scene, page, t, hit.tri.material, front, hit.b)) {
        return (seen_through_bumps(scene, hit, w, l), false);
    }
    let l = match Surface::at(scene, hit, w) {
        Some(h) if !h.absorbs && !h.bsdf.has_smooth_only() => {
            let u = u();
            let lobe = h.lobe_ray(scene, tr, [u[3], u[4], u[5]]);
            h.direct(scene, tr, [u[0], u[1], u[2]], lobe.as_ref())
        }
        _ => V::ZERO,
    };
    (l, true)
}

/// Baked light `l` of a hit seen along `w`: none where a normal map tilts the shading
/// normal away from the viewer, as the BSDF has it (a facet seen from behind reflects
/// nothing); the patch's light is the same toward every other direction. Read as stored,
/// the bumps scene's ridged floor left the image 0.7% bright with one bounce.
fn seen_through_bumps(scene: &Scene, hit: &Hit, w: V, l: V) -> V {
    if !scene.textures.bumped(hit.tri.material) {
        return l;
    }
    match Surface::at(scene, hit, w) {
        Some(s) if s.wo_l.z > 0.0 => l,
        _ => V::ZERO,
    }
}

/// The baked light of the finest patch at barycentrics `b` of triangle `t`, when the bake
/// holds what x sees there: the front of a purely diffuse surface.
fn baked_light(
    scene: &Scene,
    page: &Page,
    t: usize,
    material: u32,
    front: bool,
    b: [f32; 3],
) -> Option<V> {
    if !front || !scene.materials.get(material as usize)?.is_pure_diffuse() {
        return None;
    }
    let (k, base) = page.baked.patches_of(t)?;
    let (mut b, mut index) = (b, 0);
    for _ in 0..k {
        let (child, next) = patch::locate(b);
        (b, index) = (next, 4 * index + child);
    }
    let at = base + patch::level_start(k) + index;
    page.baked.patches.get(at).map(|&l| V::from(l))
}

/// A direction sampled from a surface's rough specular lobes, and what it hit: the BSDF
/// strategy of the surface's direct light (MIS) and, at x, the glossy bounce's exact ray.
pub(super) struct LobeRay {
    pub(super) w: V,
    /// f · cos / pdf.
    pub(super) weight: V,
    pdf: f32,
    pub(super) hit: Option<Hit>,
    /// It left the scene (toward the environment).
    left: bool,
}

/// A hit prepared for shading: the shading layer's point.
pub(super) type Surface = ShadingPoint;

impl Surface {
    /// The hit seen along `d`, its material looked up at the camera's footprint; None on a
    /// degenerate triangle.
    pub(super) fn at(scene: &Scene, hit: &Hit, d: V) -> Option<Surface> {
        let ng_raw = hit.ng();
        let len = ng_raw.length();
        if len.is_nan() || len <= 0.0 {
            return None;
        }
        let shaded = scene.material_at_hit(hit, d);
        Some(ShadingPoint::new(
            hit,
            ng_raw / len,
            -d.normalize(),
            &shaded,
        ))
    }

    /// The diffuse lobe's value (the same for every pair of directions).
    pub(super) fn diffuse_lobe(&self) -> V {
        self.bsdf.diffuse_lobe(self.wo_l)
    }

    /// The BSDF without its diffuse lobe.
    pub(super) fn glossy(&self) -> Bsdf {
        self.bsdf.glossy()
    }

    /// Whether the surface has rough specular lobes, which `lobe_ray` samples.
    pub(super) fn has_rough_lobes(&self) -> bool {
        !self.glossy().has_smooth_only()
    }

    /// A direction sampled from the rough specular lobes with `u`, traced; None where
    /// there are none (or the sample is a delta, or leaves below the surface).
    pub(super) fn lobe_ray(&self, scene: &Scene, tr: &mut Tracer, u: [f32; 3]) -> Option<LobeRay> {
        let bs = self.glossy().sample(self.wo_l, u[0], [u[1], u[2]])?;
        let w = self.frame.to_world(bs.wi).normalize();
        if bs.delta || !on_side(&self.frame, self.n, w) {
            return None;
        }
        let mut ray = Ray {
            o: offset_origin(self.p, self.err, self.ng, w),
            d: w,
            t_max: f32::INFINITY,
        };
        let (hit, left, through) = match scattering_hit(scene, tr, &mut ray, hole_number(w), &mut 0)
        {
            Ok(s) => {
                let through = scene.transmittance_to(&s.hit, w, s.travelled + s.hit.t);
                (Some(s.hit), false, through)
            }
            Err(missed) => (None, missed == Missed::Left, V::ONE),
        };
        Some(LobeRay {
            w,
            weight: bs.weight * through,
            pdf: bs.pdf,
            hit,
            left,
        })
    }

    /// Reflected direct light toward `wo` (the cloud holds no emission, so this is all of
    /// it): one light sample, and the emission `lobe` found (None where the lobes' sample
    /// failed or there are no rough lobes); the glossy lobes weigh the two
    /// by the power heuristic, as the path tracer does, the diffuse lobe (which no lobe ray
    /// samples) takes the light sample at full weight.
    pub(super) fn direct(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        u: [f32; 3],
        lobe: Option<&LobeRay>,
    ) -> V {
        let all = bsdf_term(self.frame, self.n, self.bsdf, self.wo_l);
        let glossy = bsdf_term(self.frame, self.n, self.glossy(), self.wo_l);
        let at = Receiver::surface(self.p, self.err, self.ng);
        // The light sample's weight depends on the lobes, not on whether this sample's
        // lobe ray left above the surface: full weight where one did not overstated it.
        let rough = self.has_rough_lobes();
        let light = sample_light_weighted(scene, tr, &at, &Cone::EXACT, u, |wi, pdf_l| {
            let f = all(wi).0;
            if rough {
                let (g, pdf_g) = glossy(wi);
                f - g + g * mis_weight(pdf_l, pdf_g)
            } else {
                f
            }
        });
        light + lobe.map_or(V::ZERO, |r| self.lobe_emission(scene, r))
    }

    /// The emission lobe ray `r` found (or the environment's light, where it left the
    /// scene), weighed against the light sample (power heuristic).
    fn lobe_emission(&self, scene: &Scene, r: &LobeRay) -> V {
        let from = (self.p, self.ng);
        let Some(hit) = &r.hit else {
            return match r.left {
                true => r.weight * escaped_light(scene, r.w, Some((from, r.pdf))),
                false => V::ZERO,
            };
        };
        let ng_raw = hit.ng();
        let area = 0.5 * ng_raw.length();
        if area.is_nan() || area <= 0.0 {
            return V::ZERO;
        }
        let ng = ng_raw / (2.0 * area);
        let le = scene.material_at_hit(hit, r.w).m.emitted(ng.dot(r.w) < 0.0);
        if le == V::ZERO {
            return V::ZERO;
        }
        let dist2 = hit.t * hit.t;
        r.weight * le * emission_weight(scene, hit, (ng, area), r.w, from, r.pdf, dist2)
    }
}

/// A triangle's albedo and shading normal at its points, as the path tracer shades there:
/// the albedo filtered over a patch's side, normal maps read at level 0 as always (the
/// triangle's mean albedo and geometric normal left the bumps scene 3% bright).
pub(super) struct Shading<'a> {
    scene: &'a Scene,
    t: &'a crate::paging::TriW,
    c: Corners,
    ng: V,
    /// The mean albedo, for a material that does not vary over the surface.
    rho: V,
    /// The albedo varies over the triangle (textures or vertex colours).
    textured: bool,
}

impl<'a> Shading<'a> {
    pub(super) fn new(scene: &'a Scene, (t, c): (&'a crate::paging::TriW, Corners), ng: V) -> Self {
        Shading {
            scene,
            t,
            c,
            ng,
            rho: scene.mean_material(t.material).bsdf(true).diffuse,
            textured: scene.textures.varies(t.material) || c.colour != [WHITE; 3],
        }
    }

    /// The diffuse albedo and shading normal at point q, a patch of `side` around it.
    pub(super) fn at(&self, q: V, side: f32) -> (V, V) {
        if !self.textured {
            return (self.rho, self.ng);
        }
        let v = self.t.p.map(V::from);
        let b = patch::barycentrics(v, q);
        let shaded = self
            .scene
            .material_at(self.t.material, &self.t.p, &self.c, b, -self.ng, side);
        let n = shaded.normal.unwrap_or(self.ng);
        (shaded.m.bsdf(true).diffuse, n)
    }
}

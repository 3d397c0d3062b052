//! Direct light, once for every integrator: one light sample at a receiver with its
//! visibility (through alpha holes), the MIS weights that combine it with BSDF sampling
//! (Veach 1997 §9.2), and the weight of emission a BSDF-sampled ray meets.

use super::{on_side, Scene};
use crate::material::{Bsdf, Frame};
use crate::texture::Lookup;
use crate::trace::{offset_origin, Cone, Hit, Ray, Tracer};
use glam::Vec3A as V;

/// Veach's power heuristic (β = 2) for two sampling strategies' pdfs.
pub fn power_heuristic(a: f32, b: f32) -> f32 {
    let (a2, b2) = (a * a, b * b);
    if a2 + b2 > 0.0 {
        a2 / (a2 + b2)
    } else {
        0.0
    }
}

/// The power heuristic's weight of a light sample of solid-angle pdf `pdf_l` against a
/// BSDF strategy of pdf `pdf_b`; 1 for a delta light (pdf 0), which no BSDF sample finds.
pub fn mis_weight(pdf_l: f32, pdf_b: f32) -> f32 {
    if pdf_l > 0.0 {
        power_heuristic(pdf_l, pdf_b)
    } else {
        1.0
    }
}

/// The MIS weight of emission `le` that a BSDF-sampled ray of pdf `bsdf_pdf` met at `hit`
/// (unit geometric normal `ng`, triangle area `area`) at squared distance `dist2` from
/// `from` (the point and normal whose light sample could have chosen it): the power
/// heuristic against the light sampler's pdf for that point of that emitter.
pub fn emission_weight(
    scene: &Scene,
    hit: &Hit,
    (ng, area): (V, f32),
    w: V,
    from: (V, V),
    bsdf_pdf: f32,
    dist2: f32,
) -> f32 {
    let lights = &scene.lights;
    let emitter = lights.emitter_at(hit.leaf, hit.slot);
    let light_pdf = lights.pdf_li(from, emitter, dist2, ng.dot(w).abs(), area);
    power_heuristic(bsdf_pdf, light_pdf)
}

/// The environment's light that a ray leaving the scene along `d` meets: whole for a
/// camera ray or after a delta bounce (`from` None), else weighed by the power heuristic
/// of the BSDF sample's pdf at `from` (point and normal) against the light sampler's pdf
/// for that direction.
pub fn escaped_light(scene: &Scene, d: V, from: Option<((V, V), f32)>) -> V {
    let lights = &scene.lights;
    if lights.env.is_none() {
        return V::ZERO;
    }
    let d = d.normalize();
    let le = lights.escaped(d);
    match from {
        None => le,
        Some((at, bsdf_pdf)) => le * power_heuristic(bsdf_pdf, lights.pdf_env(at, d)),
    }
}

/// `f` for `sample_light` at a surface with this BSDF: (value · |cos θ|, pdf) for a
/// direction, in the frame whose local outgoing direction is `wo_l`; zero where the
/// direction is not `on_side` of the geometric normal `n` (turned to the frame's side).
pub fn bsdf_term(frame: Frame, n: V, bsdf: Bsdf, wo_l: V) -> impl Fn(V) -> (V, f32) {
    move |wi| {
        if !on_side(&frame, n, wi) {
            return (V::ZERO, 0.0);
        }
        let wl = frame.to_local(wi);
        let (f, pdf) = bsdf.eval(wo_l, wl);
        (f * wl.z.abs(), pdf)
    }
}

/// Where a light sample is taken.
pub struct Receiver {
    pub p: V,
    /// The error bound of `p`.
    pub err: V,
    /// Unit geometric normal, for the shadow ray's offset.
    pub n: V,
    /// The normal the light chooser may weigh by |cos θ| (zero when the surface takes light
    /// from below its normal too, as a cluster's Θ does).
    pub facing: V,
    /// Light nearer than this counts as if at this distance (1/d² clamped).
    pub min_dist: f32,
}

impl Receiver {
    /// A triangle's point with its exact normal.
    pub fn surface(p: V, err: V, n: V) -> Receiver {
        Receiver {
            p,
            err,
            n,
            facing: n,
            min_dist: 0.0,
        }
    }
}

/// One light sample with MIS against the BSDF: `f(wi)` returns (value · cos, BSDF pdf).
/// Visibility is tested with `shadow_cone` (scale 0: an exact ray; the cone integrator uses
/// the pixel's opening, so distant occluders are tested at a coarse level and far pages
/// need not load).
pub fn sample_light(
    scene: &Scene,
    tr: &mut Tracer,
    at: &Receiver,
    shadow_cone: &Cone,
    u: [f32; 3],
    f: impl Fn(V) -> (V, f32),
) -> V {
    sample_light_weighted(scene, tr, at, shadow_cone, u, |wi, pdf_l| {
        let (fv, pdf_b) = f(wi);
        fv * mis_weight(pdf_l, pdf_b)
    })
}

/// One light sample: `f(wi, pdf_l)` returns value · cos with its MIS weight applied, given
/// the light sample's solid-angle pdf (0 for a delta light), so a caller may weigh lobes
/// apart (PBGI samples only the glossy ones).
pub fn sample_light_weighted(
    scene: &Scene,
    tr: &mut Tracer,
    at: &Receiver,
    shadow_cone: &Cone,
    u: [f32; 3],
    f: impl Fn(V, f32) -> V,
) -> V {
    let Some(ls) = scene.lights.sample(at.p, at.facing, u[0], [u[1], u[2]]) else {
        return V::ZERO;
    };
    let fv = f(ls.wi, ls.pdf);
    if fv.max_element() <= 0.0 {
        return V::ZERO;
    }
    let from = offset_origin(at.p, at.err, at.n, ls.wi);
    let seen = transmittance(scene, tr, ls.shadow_ray(from), shadow_cone);
    if seen <= 0.0 {
        return V::ZERO;
    }
    let clamp = if ls.dist < at.min_dist {
        (ls.dist / at.min_dist).powi(2)
    } else {
        1.0
    };
    let le = match ls.texel {
        Some((m, uv)) => {
            ls.weight
                * scene
                    .textures
                    .emission_ratio(&mut Lookup::new(&scene.cache), m, uv)
        }
        None => ls.weight,
    };
    fv * le * clamp * seen
}

/// The fraction of light a shadow ray carries: 0 or 1, or between under alpha blend. With
/// alpha materials an exact ray looks through holes, up to `MAX_PASSES` of them (a shadow
/// cone treats every surface as opaque).
fn transmittance(scene: &Scene, tr: &mut Tracer, mut ray: Ray, cone: &Cone) -> f32 {
    if cone.scale > 0.0 || !scene.textures.has_alpha() {
        return if tr.cone_occluded(&ray, cone) {
            0.0
        } else {
            1.0
        };
    }
    let mut seen = 1.0f32;
    for _ in 0..super::surface::MAX_PASSES {
        let Some(hit) = tr.closest_hit(&ray) else {
            return seen;
        };
        let opacity = scene.opacity_at(&hit);
        seen *= 1.0 - opacity;
        let n = hit.ng();
        if seen <= 0.0 || n == V::ZERO {
            return 0.0;
        }
        let (p, err) = hit.point();
        ray.o = offset_origin(p, err, n.normalize(), ray.d);
        ray.t_max -= hit.t;
    }
    0.0
}

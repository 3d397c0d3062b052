//! Light cells as the transfer's gather elements, each on one side of the surface: a cell
//! of a large triangle (`light_store::Keys`, the cells the cone integrator stores light in:
//! a triangle's n×n grid over its barycentrics, n from its size), or a whole leaf where its
//! triangles are smaller than a cell (a scan's fine triangles would otherwise each be a
//! cell, and gathering light costs rays per cell). A cell's light is the mean of the direct
//! light arriving where the transfer's paths land in it, gathered at points drawn from
//! those landings (`transfer`, `precompute`).

use crate::integrator::direct::{emission_weight, escaped_light};
use crate::integrator::surface::{scattering_hit, Missed};
use crate::integrator::{mis_weight, sample_light_weighted, Receiver, Scene};
use crate::light_store::Keys;
use crate::material::{cosine_hemisphere, Frame};
use crate::paging::{NodeRef, Page, TriW};
use crate::sampler::PixelSampler;
use crate::trace::{offset_origin, Cone, Hit, Ray, Tracer};
use canopy_format::codec::snorm16_decode;
use glam::Vec3A as V;
use std::f32::consts::FRAC_1_PI;

/// Fewest points a cell gathers light at, and most.
const MIN_POINTS: usize = 4;
const MAX_POINTS: usize = 4096;
/// Gather points per cell on average: besides each cell's least, the rest go to cells by
/// the transfer they carry over the whole image, so the light of a cell many pixels read
/// (whose noise no pixel averages away) is gathered at many points.
const MEAN_POINTS: usize = 8;

/// A point where light is gathered: position, unit geometric normal of the side lit, and
/// the unit shading normal there (normal maps applied), which the diffuse lobe's cosine
/// takes, as the path tracer's does.
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct GatherPoint {
    pub p: [f32; 3],
    pub n: [f32; 3],
    pub s: [f32; 3],
}

/// How many points each cell gathers at, given the transfer each carries summed over the
/// image (luminance).
pub fn counts(carried: &[f32]) -> Vec<usize> {
    let total: f64 = carried.iter().map(|&c| c as f64).sum();
    let spare = ((MEAN_POINTS - MIN_POINTS) * carried.len()) as f64;
    carried
        .iter()
        .map(|&c| {
            let share = if total > 0.0 { c as f64 / total } else { 0.0 };
            MIN_POINTS + ((share * spare).ceil() as usize).min(MAX_POINTS - MIN_POINTS)
        })
        .collect()
}

/// Leaves whose triangles' area-weighted mean winding normal is at least this long (1: all
/// face one way) are one cell a side; the triangles of other leaves keep a cell each.
const COHERENT: f32 = 0.9;

/// The cell a hit on its `back` side (or front) lands in: the triangle's cell; or, where
/// the triangle is a single cell and its leaf's triangles face one way, the leaf's side
/// (the key after the leaf's own, the back after that: keys the store leaves unused),
/// taken against the leaf's mean normal whatever the winding of the triangle hit. A
/// prototype's leaf is keyed as the hit's instance places it, so copies in different light
/// keep their own cells.
pub fn key(tr: &mut Tracer, keys: &Keys, hit: &Hit, back: bool) -> u64 {
    let leaf = keys.placed(hit.instance, hit.leaf);
    if keys.grid(&hit.tri) > 1.0 {
        return keys.tri(leaf, hit.slot, back, keys.cell_of(&hit.tri, hit.b));
    }
    let page = tr.page_handle(hit.page);
    match coherent_leaf(&page, hit.leaf) {
        Some((mean, first)) => {
            let flip = page
                .tri(first + hit.slot)
                .is_some_and(|t| opposed(&t, mean));
            keys.node(leaf) + 1 + (back ^ flip) as u64
        }
        None => keys.tri(leaf, hit.slot, back, 0),
    }
}

/// A leaf (global node `leaf` of `page`) whose triangles face one way: its mean winding
/// normal and first triangle.
fn coherent_leaf(page: &Page, leaf: u64) -> Option<(V, u32)> {
    let local = leaf.checked_sub(page.first_node)? as usize;
    let mean = V::from(page.nodes.get(local)?.normal.map(snorm16_decode));
    let Some(NodeRef::Leaf { first, .. }) = page.bvh.get(local).map(|n| n.link()) else {
        return None;
    };
    (mean.length() >= COHERENT).then_some((mean, first))
}

/// Whether `t` is wound against `normal` (its winding normal points away from it).
fn opposed(t: &TriW, normal: V) -> bool {
    let p = t.p.map(V::from);
    (p[1] - p[0]).cross(p[2] - p[0]).dot(normal) < 0.0
}

/// E/π arriving at gather point `p` from the scene's lights: a light sample and, where the
/// lights have area (lamps, the environment), a cosine-distributed ray that may meet them,
/// combined by the power heuristic (Veach 1997 §9.2; numbers from `s`'s sets 0 and 1). A
/// point close to a lamp, whose light samples alone are heavy-tailed, is then estimated as
/// the path tracer estimates it.
pub fn arriving(scene: &Scene, tr: &mut Tracer, p: &GatherPoint, s: &PixelSampler) -> V {
    let (at, n, shading) = (V::from(p.p), V::from(p.n), V::from(p.s));
    let err = at.abs() * crate::trace::gamma(7);
    // The diffuse lobe's cosine, on the lit side of both normals, over π: also the pdf of
    // the cosine-distributed ray.
    let cosine = |wi: V| match n.dot(wi) > 0.0 {
        true => shading.dot(wi).max(0.0) * FRAC_1_PI,
        false => 0.0,
    };
    let rec = Receiver::surface(at, err, n);
    let [u0, u1, u2, _] = s.get4(0);
    let sampled = sample_light_weighted(scene, tr, &rec, &Cone::EXACT, [u0, u1, u2], |wi, pdf| {
        V::splat(cosine(wi) * mis_weight(pdf, cosine(wi)))
    });
    let [u3, u4, u5, _] = s.get4(1);
    let wi = Frame::new(shading)
        .to_world(cosine_hemisphere([u3, u4]))
        .normalize();
    let pdf = cosine(wi);
    if pdf <= 0.0 {
        return sampled;
    }
    // The cosine over π is the ray's pdf, so its estimate of E/π is the radiance it meets.
    sampled + met_light(scene, tr, (at, err, n), wi, Some(pdf), u5)
}

/// The light of the scene's lamps and environment that a ray from `from` (point, error
/// bound, unit normal of the side it leaves) along unit `wi` meets (`u` decides alpha
/// holes): a lamp's own emission (a textured lamp's mean) on a face it emits from, or the
/// environment, weighed against the light sampler by the power heuristic for a ray drawn
/// with solid-angle pdf `pdf` (Veach 1997 §9.2). A ray drawn from a delta lobe (`pdf`
/// None) meets the environment whole and no lamp: a lamp met after a smooth bounce is a
/// pixel's lamp record.
pub fn met_light(
    scene: &Scene,
    tr: &mut Tracer,
    (at, err, n): (V, V, V),
    wi: V,
    pdf: Option<f32>,
    u: f32,
) -> V {
    let lights = &scene.lights;
    if !lights.has_area() {
        return V::ZERO;
    }
    let mut ray = Ray {
        o: offset_origin(at, err, n, wi),
        d: wi,
        t_max: f32::INFINITY,
    };
    match (scattering_hit(scene, tr, &mut ray, u, &mut 0), pdf) {
        (Ok(s), Some(pdf)) => {
            let lamp = lights.emitter_at(s.hit.leaf, s.hit.slot);
            match lamp.map(|i| &lights.emitters[i as usize]) {
                // One of the share's lamps, met on a face it emits from.
                Some(e) if e.n.dot(wi) < 0.0 || e.two_sided => {
                    let d2 = s.length(&ray).powi(2);
                    let w = emission_weight(scene, &s.hit, (s.ng, s.area), wi, (at, n), pdf, d2);
                    e.le * w
                }
                _ => V::ZERO,
            }
        }
        (Err(Missed::Left), pdf) => escaped_light(scene, wi, pdf.map(|p| ((at, n), p))),
        _ => V::ZERO,
    }
}

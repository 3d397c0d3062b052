//! The transfer from light arriving at the scene's surfaces to a pixel, all bounces
//! included (001 §4.4's global transport operator, gathered as Hašan et al. 2006 §4 do):
//! paths leave each view sample by BSDF sampling; at every surface they meet, the light
//! arriving there directly (E/π, as the cone integrator stores it) leaves through the
//! surface's diffuse lobe, and through its glossy lobes as if it arrived evenly over the
//! hemisphere, so the path's throughput times those lobes' albedo is the weight of that
//! surface's light cell in the pixel. Summed over the pixel's paths, that is
//! one row of the transfer matrix, a vector over the cells. With each weight the row keeps
//! one point where the pixel's paths landed in the cell, drawn by their weights: the
//! cell's gather points are drawn from these, so a cell's light is the mean over where
//! paths land in it, not over its whole area (parts of it no path reaches, buried in other
//! geometry, would darken it).
//!
//! The row is then compressed to a fixed number of coefficients (`compress`). 001 §4.4
//! thresholds the row's Haar coefficients; over the node tree (a node's light the
//! area-weighted mean of its children's) that was measured biased dark, −0.6% to −2.8% of
//! the image mean on bunny_box at 30 to 160 coefficients a pixel, because a coarse node's
//! mean light stands for where this pixel's paths landed in it, which is where light
//! arrives, not the far side or the floor under a box. The compression here keeps the
//! tree's order instead: systematic sampling along it is unbiased, stratified over
//! subtrees, and its noise falls as the coefficients grow (docs/relighting.md).

use super::cells::{self, GatherPoint};
use crate::integrator::surface::{scattering_hit, Missed};
use crate::integrator::{on_side, Scene, ShadingPoint};
use crate::light_store::Keys;
use crate::material::luminance;
use crate::sampler::PixelSampler;
use crate::trace::{offset_origin, Ray, Tracer};
use glam::Vec3A as V;
use rustc_hash::FxHashMap;
use std::f32::consts::PI;

/// Longest transfer path in bounces (Russian roulette ends nearly all paths long before).
const MAX_BOUNCES: u32 = 64;

/// One cell's entry in a pixel's row: the summed weight, and one landing drawn from the
/// pixel's landings in the cell by their weights (`sum` the luminance drawn over).
#[derive(Clone, Copy)]
pub struct Entry {
    pub w: V,
    sum: f32,
    pub landing: GatherPoint,
}

/// A pixel's transfer row over light cells, before compression.
pub type Row = FxHashMap<u64, Entry>;

/// A compressed row's coefficient: the cell's key, its weight, a landing in it.
pub type Coefficient = (u64, V, GatherPoint);

/// Light a transfer path meets straight after a perfectly smooth bounce or through a
/// surface (a lamp in a mirror, its light focused through glass: what no light sample
/// reaches), `weight` times what it sends along the path: a lamp's by material, or the
/// environment's along a direction (the environment's radiance there, scaled and turned
/// as a light set says, times the weight).
pub enum Met {
    Lamp(u32, V),
    Sky(V, V),
}

/// Follows one path from the view sample `sp` (throughput `beta`), adding `weight` times
/// each surface's diffuse weight to its cell in `row` with the point it landed at (the
/// side the path came from); numbers from `s`'s sets 1... Light met after a smooth bounce
/// or through a surface is told to `met`.
pub fn follow(
    scene: &Scene,
    tr: &mut Tracer,
    start: &ShadingPoint,
    mut beta: V,
    s: &PixelSampler,
    (keys, weight): (&Keys, f32),
    (row, met): (&mut Row, &mut impl FnMut(Met)),
) {
    let mut sp = *start;
    let mut passes = 0u32;
    for depth in 0..MAX_BOUNCES {
        let [u_lobe, u0, u1, u_rr] = s.get4(1 + 3 * depth);
        let [u_hole, u_land, ..] = s.get4(2 + 3 * depth);
        let [g_lobe, g0, g1, _] = s.get4(3 + 3 * depth);
        if sp.absorbs {
            return;
        }
        let Some(bs) = sp.bsdf.sample(sp.wo_l, u_lobe, [u0, u1]) else {
            return;
        };
        let wi = sp.frame.to_world(bs.wi).normalize();
        if !on_side(&sp.frame, sp.n, wi) {
            return;
        }
        beta *= bs.weight;
        // Light the path meets along a smooth lobe, or through the surface (a rough glass's
        // transmission: the cell's gather takes light from the side the path came from
        // only), is no cell's: a lamp or the environment met so is told to `met`. From the
        // view sample itself, only a lamp after a smooth bounce: its direct light samples
        // its lobes for the rest.
        let through = bs.delta || sp.n.dot(wi) < 0.0;
        let mut ray = Ray {
            o: offset_origin(sp.p, sp.err, sp.ng, wi),
            d: wi,
            t_max: f32::INFINITY,
        };
        let scatter = match scattering_hit(scene, tr, &mut ray, u_hole, &mut passes) {
            Ok(s) => s,
            Err(Missed::Left) => {
                if through && depth > 0 {
                    met(Met::Sky(wi, beta * weight));
                }
                return;
            }
            Err(Missed::Degenerate) => return,
        };
        let hit = &scatter.hit;
        sp = scatter.shading(scene, &ray);
        beta *= sp.through(scatter.length(&ray));
        if !beta.is_finite() || beta.max_element() <= 0.0 {
            return;
        }
        if (bs.delta || through && depth > 0) && sp.emitted.max_element() > 0.0 {
            met(Met::Lamp(hit.tri.material, beta * sp.emitted * weight));
        }
        let albedo = PI * sp.bsdf.diffuse_lobe(sp.wo_l) + glossy_albedo(&sp, [g_lobe, g0, g1]);
        if !sp.absorbs && albedo.max_element() > 0.0 {
            let key = cells::key(tr, keys, hit, !sp.front);
            let w = beta * albedo * weight;
            let landing = GatherPoint {
                p: sp.p.into(),
                n: sp.n.into(),
                s: sp.frame.n.into(),
            };
            add(row, key, w, landing, u_land);
        }
        let q = beta.max_element();
        if depth > 0 && q < 1.0 {
            if u_rr >= q {
                return;
            }
            beta /= q;
        }
    }
}

/// An estimate of the light `sp`'s lobes other than the diffuse reflect toward the path
/// from light arriving evenly over the hemisphere (their directional albedo at `wo`), from
/// one sample of them: direct light E/π leaves through them as if it arrived so. Exact in
/// the mean for light from every direction; a lamp's highlight on a glossy surface, seen
/// in a reflection or thrown onto another surface, is spread over the lobe's albedo.
fn glossy_albedo(sp: &ShadingPoint, [u_lobe, u0, u1]: [f32; 3]) -> V {
    sp.bsdf
        .glossy()
        .sample(sp.wo_l, u_lobe, [u0, u1])
        .filter(|g| !g.delta && g.weight.is_finite())
        .filter(|g| on_side(&sp.frame, sp.n, sp.frame.to_world(g.wi).normalize()))
        .map_or(V::ZERO, |g| g.weight)
}

/// Adds weight `w` landing at `landing` to cell `key` of `row`; the cell's landing becomes
/// this one with probability its luminance over the cell's so far (`u` uniform).
fn add(row: &mut Row, key: u64, w: V, landing: GatherPoint, u: f32) {
    let lum = luminance(w);
    let e = row.entry(key).or_insert(Entry {
        w: V::ZERO,
        sum: 0.0,
        landing,
    });
    e.w += w;
    e.sum += lum;
    if u * e.sum < lum {
        e.landing = landing;
    }
}

/// A row compressed to at most `n` coefficients by systematic sampling along the node
/// tree's order: with the cells in node order (a subtree's cells lie together), `n` evenly
/// spaced picks fall on the cumulative weight, each pick of a cell carrying the row's total
/// over `n` in that cell's colour. The estimate is unbiased and stratified over subtrees;
/// a cell heavier than a pick's share is kept with its exact weight.
pub fn compress(row: &Row, n: u32, u: f32) -> Vec<Coefficient> {
    let mut cells: Vec<(u64, Entry)> = row.iter().map(|(&k, &e)| (k, e)).collect();
    cells.sort_unstable_by_key(|c| c.0);
    let weights: Vec<V> = cells.iter().map(|c| c.1.w).collect();
    systematic(&weights, n as usize, u)
        .into_iter()
        .map(|(i, w)| (cells[i].0, w, cells[i].1.landing))
        .collect()
}

/// Systematic sampling of `n` picks over `weights` in their order, on their luminance
/// (`u` uniform, the first pick's place in a step): each weight picked, by its index, with
/// the total over `n` times its picks in its own colour. Unbiased; none when the total is
/// not positive and finite.
pub fn systematic(weights: &[V], n: usize, u: f32) -> Vec<(usize, V)> {
    let total: f32 = weights.iter().map(|&w| luminance(w)).sum();
    if total <= 0.0 || !total.is_finite() {
        return Vec::new();
    }
    let step = total / n as f32;
    let mut out = Vec::new();
    let mut next = u * step;
    let mut below = 0.0f32;
    for (i, &w) in weights.iter().enumerate() {
        let lum = luminance(w);
        if lum <= 0.0 {
            continue;
        }
        below += lum;
        let mut picks = 0u32;
        while next < below {
            picks += 1;
            next += step;
        }
        if picks > 0 {
            out.push((i, w * (picks as f32 * step / lum)));
        }
    }
    out
}

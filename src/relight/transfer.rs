//! The transfer from light arriving at the scene's surfaces to a pixel, all bounces
//! included (001 §4.4's global transport operator, gathered as Hašan et al. 2006 §4 do):
//! paths leave each view sample by BSDF sampling; at every surface they meet, the light
//! arriving there directly (E/π, diffuse, as the cone integrator stores it) leaves through
//! the surface's diffuse lobe, so the path's throughput times that lobe's albedo is the
//! weight of that surface's light cell in the pixel. Summed over the pixel's paths, that is
//! one row of the transfer matrix, a vector over the cells.
//!
//! The row is then written in the node tree's Haar basis and compressed non-linearly (001
//! §4.4): the aggregate transfer of a node is the sum of its cells' (the Haar scaling
//! coefficient), a node whose aggregate is below `threshold` times the pixel's total is
//! merged into its parent, and each node kept carries what its kept children do not. The
//! nodes kept form a tree from the root down, a cut per pixel whose depth follows the
//! pixel's transfer: fine where light arrives from near, coarse from afar.

use super::tree::{Tree, TOP};
use crate::integrator::surface::{scattering_hit, Missed};
use crate::integrator::{on_side, Scene, ShadingPoint};
use crate::material::luminance;
use crate::sampler::PixelSampler;
use crate::trace::{offset_origin, Ray, Tracer};
use glam::Vec3A as V;
use rustc_hash::FxHashMap;
use std::f32::consts::PI;

/// Longest transfer path in bounces (Russian roulette ends nearly all paths long before).
const MAX_BOUNCES: u32 = 64;

/// A pixel's transfer row over light cells, before compression.
pub type Row = FxHashMap<u64, V>;

/// Follows one path from the view sample `sp` (throughput `beta`), adding `weight` times
/// each surface's diffuse weight to its cell in `row`; numbers from `s`'s sets 1...
pub fn follow(
    scene: &Scene,
    tr: &mut Tracer,
    start: &ShadingPoint,
    mut beta: V,
    s: &PixelSampler,
    (tree, weight): (&Tree, f32),
    row: &mut Row,
) {
    let mut sp = *start;
    let mut passes = 0u32;
    for depth in 0..MAX_BOUNCES {
        let [u_lobe, u0, u1, u_rr] = s.get4(1 + 2 * depth);
        let [u_hole, ..] = s.get4(2 + 2 * depth);
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
        let mut ray = Ray {
            o: offset_origin(sp.p, sp.err, sp.ng, wi),
            d: wi,
            t_max: f32::INFINITY,
        };
        let scatter = match scattering_hit(scene, tr, &mut ray, u_hole, &mut passes) {
            Ok(s) => s,
            Err(Missed::Left | Missed::Degenerate) => return,
        };
        let hit = &scatter.hit;
        let wo = -ray.d.normalize();
        sp = ShadingPoint::new(hit, scatter.ng, wo, &scene.material_at_hit(hit, ray.d));
        beta *= sp.through(scatter.travelled + hit.t * ray.d.length());
        if !beta.is_finite() || beta.max_element() <= 0.0 {
            return;
        }
        let albedo = PI * sp.bsdf.diffuse_lobe(sp.wo_l);
        if !sp.absorbs && albedo.max_element() > 0.0 {
            let cell = tree.keys.cell_of(&hit.tri, hit.b);
            let key = tree.keys.tri(hit.leaf, hit.slot, !sp.front, cell);
            *row.entry(key).or_insert(V::ZERO) += beta * albedo * weight;
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

/// A row compressed: each kept node's key and the transfer it carries.
pub fn compress(tree: &Tree, row: &Row, threshold: f32) -> Vec<(u64, V)> {
    if row.is_empty() {
        return Vec::new();
    }
    // Aggregates of every node above the cells, and each key's parent.
    let mut total: FxHashMap<u64, V> = FxHashMap::default();
    let mut parent: FxHashMap<u64, u64> = FxHashMap::default();
    let mut chains: FxHashMap<u64, Vec<u64>> = FxHashMap::default();
    for (&cell, &w) in row {
        let leaf = tree.keys.decode(cell).0;
        let chain = chains.entry(leaf).or_insert_with(|| {
            let mut c = vec![tree.keys.node(leaf)];
            tree.ancestors(leaf, &mut c);
            c
        });
        *total.entry(cell).or_insert(V::ZERO) += w;
        parent.insert(cell, chain[0]);
        for (i, &k) in chain.iter().enumerate() {
            *total.entry(k).or_insert(V::ZERO) += w;
            if let Some(&up) = chain.get(i + 1) {
                parent.insert(k, up);
            }
        }
    }
    let floor = threshold * luminance(total[&TOP]);
    let kept = |k: &u64| luminance(total[k]) >= floor;
    let mut carried: FxHashMap<u64, V> = total
        .iter()
        .filter(|(k, _)| kept(k))
        .map(|(&k, &v)| (k, v))
        .collect();
    for (k, up) in &parent {
        if kept(k) {
            if let Some(c) = carried.get_mut(up) {
                *c -= total[k];
            }
        }
    }
    let mut out: Vec<(u64, V)> = carried
        .into_iter()
        .map(|(k, v)| (k, v.max(V::ZERO)))
        .filter(|(_, v)| v.max_element() > 0.0)
        .collect();
    out.sort_unstable_by_key(|e| e.0);
    out
}

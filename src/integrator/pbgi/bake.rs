//! The bake: direct light reflected diffusely by every node, the point cloud PBGI gathers
//! (003 ch. 2, phase 1). Leaves estimate each triangle's reflected radiance ρ·E/π with
//! light samples (light tree and shadow rays) at random points of the triangle and take
//! the area-weighted mean; inner nodes take their children's area-weighted mean, deepest
//! pages first, as `radiance::pull` does. Emission is left out: the renderer adds direct
//! light with the path tracer's estimator, so the cloud carries only what one bounce
//! reflects.

use crate::integrator::{sample_light, Receiver, Scene};
use crate::paging::{deepest_first, NodeRef, Page};
use crate::trace::{gamma, Cone, Tracer};
use glam::Vec3A as V;
use rayon::prelude::*;
use std::f32::consts::FRAC_1_PI;

const EXACT: Cone = Cone {
    r0: 0.0,
    tan_a: 0.0,
    scale: 0.0,
    spread: 0.0,
};

/// Per global node number, the radiance it reflects toward its front side.
pub struct Baked {
    pub radiance: Vec<[f32; 3]>,
    /// Light samples taken.
    pub samples: u64,
}

impl Baked {
    pub fn bytes(&self) -> u64 {
        (self.radiance.len() * std::mem::size_of::<[f32; 3]>()) as u64
    }
}

/// Bakes every page of the archive with `per_tri` light samples per triangle.
pub fn bake(scene: &Scene, per_tri: u32, seed: u32) -> Baked {
    let cache = &scene.cache;
    let archive = &cache.archive;
    let mut radiance = vec![[0.0f32; 3]; archive.header.nodes as usize];
    let mut samples = 0;
    let pages: Vec<u32> = (0..archive.pages.len() as u32).collect();
    for level in deepest_first(archive, pages) {
        let done = &radiance;
        let baked: Vec<(u64, Vec<[f32; 3]>, u64)> = level
            .par_iter()
            .map_init(
                || Tracer::new(cache),
                |tr, &id| {
                    let page = tr.page_handle(id);
                    let (vals, n) = bake_page(scene, tr, &page, done, per_tri, seed);
                    (page.first_node, vals, n)
                },
            )
            .collect();
        for (first, vals, n) in baked {
            let first = first as usize;
            if let Some(dst) = radiance.get_mut(first..first + vals.len()) {
                dst.copy_from_slice(&vals);
            }
            samples += n;
        }
    }
    Baked { radiance, samples }
}

fn weighted(parts: &[([f32; 3], f32)]) -> [f32; 3] {
    let total: f32 = parts.iter().map(|p| p.1).sum();
    if total <= 0.0 {
        return [0.0; 3];
    }
    let sum = parts.iter().fold(V::ZERO, |s, p| s + V::from(p.0) * p.1);
    (sum / total).into()
}

/// One page's nodes, children before parents (a page stores parents first); child pages
/// are already in `done`.
fn bake_page(
    scene: &Scene,
    tr: &mut Tracer,
    page: &Page,
    done: &[[f32; 3]],
    per_tri: u32,
    seed: u32,
) -> (Vec<[f32; 3]>, u64) {
    let mut vals = vec![[0.0f32; 3]; page.bvh.len()];
    let mut samples = 0;
    for i in (0..page.bvh.len()).rev() {
        let area = |p: &Page, k: u32| p.nodes.get(k as usize).map_or(0.0, |n| n.area);
        vals[i] = match page.bvh[i].link() {
            NodeRef::Leaf { first, count } => {
                let end = (first + count).min(page.tris.len() as u32);
                let parts: Vec<([f32; 3], f32)> = (first..end)
                    .map(|k| {
                        let key = (page.first_node + i as u64) << 4 | (k - first) as u64;
                        samples += per_tri as u64;
                        triangle(scene, tr, &page.tris[k as usize], per_tri, seed, key)
                    })
                    .collect();
                weighted(&parts)
            }
            NodeRef::Inner(l, r) => weighted(&[
                (vals[l as usize], area(page, l)),
                (vals[r as usize], area(page, r)),
            ]),
            NodeRef::ChildPage(c) => {
                let child = tr.page_handle(c);
                let at = |k: u32| {
                    done.get((child.first_node + k as u64) as usize)
                        .copied()
                        .unwrap_or_default()
                };
                weighted(&[(at(0), area(&child, 0)), (at(1), area(&child, 1))])
            }
        };
    }
    (vals, samples)
}

/// A triangle's reflected radiance ρ·E/π and its area.
fn triangle(
    scene: &Scene,
    tr: &mut Tracer,
    t: &crate::paging::TriW,
    n: u32,
    seed: u32,
    key: u64,
) -> ([f32; 3], f32) {
    let p = t.p.map(V::from);
    let cross = (p[1] - p[0]).cross(p[2] - p[0]);
    let area = 0.5 * cross.length();
    let m = &scene.materials[t.material as usize];
    let rho = m.bsdf(true).diffuse;
    if area.is_nan() || area <= 0.0 || rho.max_element() <= 0.0 || n == 0 {
        return ([0.0; 3], area.max(0.0));
    }
    let ng = cross / (2.0 * area);
    let mut rng = Hash::new(seed as u64 ^ key.wrapping_mul(0x9E37_79B9_7F4A_7C15));
    let mut sum = V::ZERO;
    for _ in 0..n {
        let (mut a, mut b) = (rng.f32(), rng.f32());
        if a + b > 1.0 {
            (a, b) = (1.0 - a, 1.0 - b);
        }
        let q = p[0] + (p[1] - p[0]) * a + (p[2] - p[0]) * b;
        let err = (p[0].abs() + p[1].abs() + p[2].abs()) * gamma(7);
        // Light sampling alone (BSDF pdf 0 gives it full weight): nothing else samples
        // the emitters here.
        sum += sample_light(
            scene,
            tr,
            &Receiver::surface(q, err, ng),
            &EXACT,
            [rng.f32(), rng.f32(), rng.f32()],
            |wi| (rho * (FRAC_1_PI * ng.dot(wi).max(0.0)), 0.0),
        );
    }
    ((sum / n as f32).into(), area)
}

/// SplitMix64: independent uniforms per triangle without a shared generator.
pub struct Hash(u64);

impl Hash {
    pub fn new(seed: u64) -> Hash {
        Hash(seed)
    }

    pub fn f32(&mut self) -> f32 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        (z >> 40) as f32 / (1u64 << 24) as f32
    }
}

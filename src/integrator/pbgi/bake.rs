//! The bake: direct light reflected diffusely by every node, the point cloud PBGI gathers
//! (003 ch. 2, phase 1). Leaves estimate each triangle's reflected radiance ρ·E/π with
//! light samples (light tree and shadow rays) at random points of the triangle. Emission
//! is left out: the renderer adds direct light with the path tracer's estimator, so the
//! cloud carries only what one bounce reflects.
//!
//! A node keeps what it shows each way, not one mean: per cube axis a_k, its projected
//! area P_k = Σ A·max(0, n·a_k) and reflected power Q_k = Σ A·B·max(0, n·a_k) over its
//! triangles (both add up the tree, deepest pages first). Seen from ω they are blended
//! with the weights max(0, ±ω_axis)², which sum to one (an "ambient cube"; Christensen
//! 2008 projects the same two quantities on spherical harmonics). A node that sent its
//! mean light every way, covering A·Θ/d² (004 eq. 4.4), overstated the bunny's indirect
//! light on bunny_box by half (README).

use crate::integrator::{sample_light, Receiver, Scene};
use crate::paging::{deepest_first, NodeRef, Page};
use crate::trace::{gamma, Cone, Tracer};
use glam::Vec3A as V;
use rayon::prelude::*;
use std::f32::consts::FRAC_1_PI;

/// What a node shows along each cube axis (+x, −x, +y, −y, +z, −z).
#[derive(Clone, Copy, Debug, Default)]
pub struct Directional {
    /// Projected area P_k.
    pub area: [f32; 6],
    /// Reflected power Q_k (radiance times projected area).
    pub power: [[f32; 3]; 6],
}

impl Directional {
    fn add(&mut self, o: &Directional) {
        for k in 0..6 {
            self.area[k] += o.area[k];
            self.power[k] = (V::from(self.power[k]) + V::from(o.power[k])).into();
        }
    }

    /// A surface of area `a`, unit normal `n`, reflecting radiance `b`.
    fn patch(a: f32, n: V, b: V) -> Directional {
        let mut d = Directional::default();
        for (k, w) in axis_cosines(n).into_iter().enumerate() {
            d.area[k] = a * w;
            d.power[k] = (b * (a * w)).into();
        }
        d
    }

    /// Projected area and reflected power seen from direction `w` (unit, node → viewer).
    pub fn toward(&self, w: V) -> (f32, V) {
        let mut area = 0.0;
        let mut power = V::ZERO;
        for (k, c) in axis_cosines(w).into_iter().enumerate() {
            let wk = c * c;
            area += wk * self.area[k];
            power += V::from(self.power[k]) * wk;
        }
        (area, power)
    }
}

/// max(0, ±v) per axis, in the order +x, −x, +y, −y, +z, −z.
fn axis_cosines(v: V) -> [f32; 6] {
    [
        v.x.max(0.0),
        (-v.x).max(0.0),
        v.y.max(0.0),
        (-v.y).max(0.0),
        v.z.max(0.0),
        (-v.z).max(0.0),
    ]
}

/// Per global node number, what it shows each way.
pub struct Baked {
    pub radiance: Vec<Directional>,
    /// Light samples taken.
    pub samples: u64,
}

impl Baked {
    pub fn bytes(&self) -> u64 {
        (self.radiance.len() * std::mem::size_of::<Directional>()) as u64
    }
}

/// Bakes every page of the archive with `per_tri` light samples per triangle.
pub fn bake(scene: &Scene, per_tri: u32, seed: u32) -> Baked {
    let cache = &scene.cache;
    let archive = &cache.archive;
    let mut radiance = vec![Directional::default(); archive.header.nodes as usize];
    let mut samples = 0;
    let pages: Vec<u32> = (0..archive.pages.len() as u32).collect();
    for level in deepest_first(archive, pages) {
        let done = &radiance;
        let baked: Vec<(u64, Vec<Directional>, u64)> = level
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

/// One page's nodes, children before parents (a page stores parents first); child pages
/// are already in `done`.
fn bake_page(
    scene: &Scene,
    tr: &mut Tracer,
    page: &Page,
    done: &[Directional],
    per_tri: u32,
    seed: u32,
) -> (Vec<Directional>, u64) {
    let mut vals = vec![Directional::default(); page.bvh.len()];
    let mut samples = 0;
    for i in (0..page.bvh.len()).rev() {
        let mut d = Directional::default();
        match page.bvh[i].link() {
            NodeRef::Leaf { first, count } => {
                for k in first..(first + count).min(page.tris.len() as u32) {
                    let key = ((page.first_node + i as u64) << 4) | (k - first) as u64;
                    samples += per_tri as u64;
                    d.add(&triangle(
                        scene,
                        tr,
                        &page.tris[k as usize],
                        per_tri,
                        seed,
                        key,
                    ));
                }
            }
            NodeRef::Inner(l, r) => {
                d.add(&vals[l as usize]);
                d.add(&vals[r as usize]);
            }
            NodeRef::ChildPage(c) => {
                let first = tr.page_handle(c).first_node as usize;
                for k in first..first + 2 {
                    d.add(&done.get(k).copied().unwrap_or_default());
                }
            }
        }
        vals[i] = d;
    }
    (vals, samples)
}

/// A triangle's reflected radiance ρ·E/π, as a patch.
fn triangle(
    scene: &Scene,
    tr: &mut Tracer,
    t: &crate::paging::TriW,
    n: u32,
    seed: u32,
    key: u64,
) -> Directional {
    let p = t.p.map(V::from);
    let cross = (p[1] - p[0]).cross(p[2] - p[0]);
    let area = 0.5 * cross.length();
    let m = &scene.materials[t.material as usize];
    let rho = m.bsdf(true).diffuse;
    if area.is_nan() || area <= 0.0 {
        return Directional::default();
    }
    let ng = cross / (2.0 * area);
    if rho.max_element() <= 0.0 || n == 0 {
        return Directional::patch(area, ng, V::ZERO);
    }
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
            &Cone::EXACT,
            [rng.f32(), rng.f32(), rng.f32()],
            |wi| (rho * (FRAC_1_PI * ng.dot(wi).max(0.0)), 0.0),
        );
    }
    Directional::patch(area, ng, sum / n as f32)
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_patch_shows_its_area_along_each_axis_and_nothing_behind() {
        let b = V::new(1.0, 2.0, 3.0);
        for n in [V::X, V::NEG_Y, V::Z] {
            let d = Directional::patch(2.0, n, b);
            let (area, power) = d.toward(n);
            assert!((area - 2.0).abs() < 1e-6 && (power - b * 2.0).abs().max_element() < 1e-6);
            assert_eq!(d.toward(-n).0, 0.0);
        }
        // An oblique patch seen along its normal shows A·Σ|n_k|³ (the blend's loss at
        // oblique views), and its own light from every front direction.
        let n = V::new(1.0, 2.0, -2.0).normalize();
        let d = Directional::patch(3.0, n, b);
        let (area, _) = d.toward(n);
        assert!((area - 3.0 * 17.0 / 27.0).abs() < 1e-5, "{area}");
        for w in [
            n,
            V::new(1.0, 1.0, -0.2).normalize(),
            V::new(0.1, 0.3, -0.9).normalize(),
        ] {
            let (area, power) = d.toward(w);
            assert!(area > 0.0 && (power / area - b).abs().max_element() < 1e-5);
        }
    }

    #[test]
    fn nodes_add_their_childrens_area_and_power() {
        let mut sum = Directional::patch(1.0, V::X, V::ONE);
        sum.add(&Directional::patch(1.0, V::NEG_X, V::ZERO));
        let w = V::new(1.0, 1.0, 0.0).normalize();
        let (area, power) = sum.toward(w);
        // Half of the +x patch's area along x's cosine, 1/√2, squared: 0.5.
        assert!((area - 0.5).abs() < 1e-6, "{area}");
        assert!((power.x - area).abs() < 1e-6);
        // Seen along −x only the dark patch shows.
        assert_eq!(sum.toward(V::NEG_X).1, V::ZERO);
    }
}
